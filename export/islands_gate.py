"""Choosing bf16's float32 islands by measurement, where plain bf16 fails its accuracy gate (issue 41 item 2).

The candidates are the graph's units (export/islands.search_units): each module two levels down ("/flow/match/") and
each scope's own nodes ("/propagation/*"). The units without a matrix operation are float32 from the start: bf16
speeds up nothing there, and they hold the poses, the sampling positions, GridSample and the decode's top-k, where
its rounding moves things most. The matrix units grow by greedy forward selection: at each step every unit not yet
chosen is tried, added to the islands so far, on a short gate of simulated drives apart from the gate's
(SEARCH_SEED), and the best by `rank` joins: of those whose accuracy checks pass, the one that moves the matched
detections least (`perturbation`: there a short gate's flip counts are a handful of events, its matched quantiles are
not), else the one least over the limits (`excess`). The matrix-free units alone are tried first. When a set's short
gate passes its accuracy checks, the full gate (the same as plain bf16's) judges it, and the first set the full gate
passes is kept: as much of the graph's matrix work in bf16 as passes, among the sets the search tries. Every matrix
unit in float32 is no bf16 at all, so the search stops one short of it. The passing set's segments stay beside the
model (MODEL.bf16-islands/) and its record names them (GateReport.islands, islands_sha256); every gate the search ran
is in the record too (GateReport.search).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from export.gate import GateOptions, GateReport, gate_model
from export.islands import replace_dir, search_units, write_islands
from rafd.model_files import islands_dir, islands_sha256

SEARCH_SEED = 7200  # apart from the gate's (export.gate.DEFAULT_SEED), int8 calibration's and training's
NOT_FINITE = 1e6  # the excess of a check whose figure is not finite (the arithmetic broke)

# (onnx_path, islands folder, sequences, frames, seed, radiate) -> report: the gate of one islands set
IslandsGate = Callable[[Path, Path, int, int, int, "str | Path | None"], GateReport]


def excess(report: GateReport) -> float:
    """How far a report's accuracy checks are over their limits: the sum of value / limit over the checks that
    compare outputs (not the evidence counts), a non-finite figure counting NOT_FINITE. Lower is closer to passing."""
    total = 0.0
    for _, check, value, limit, _ in report.checks():
        if check.endswith("(at least)"):
            continue
        total += value / limit if math.isfinite(value) and limit > 0 else NOT_FINITE
    return total


def perturbation(report: GateReport) -> float:
    """How far the candidate moves the detections both keep: the sum of value / limit over the matched-detection
    quantiles (centre shift p99, score difference p99), a non-finite one counting NOT_FINITE. The search ranks its
    short gates by it: quantiles over hundreds of matched detections resolve what the flip counts cannot (changed
    detections and mAP are a handful of events on a short gate), and the flips come from the same movement, of the
    scores near the threshold."""
    total = 0.0
    for _, check, value, limit, _ in report.checks():
        if check.startswith("matched "):
            total += value / limit if math.isfinite(value) and limit > 0 else NOT_FINITE
    return total


def rank(report: GateReport) -> tuple[int, float, float]:
    """The order of a step's short gates, best first: those that pass their accuracy checks before those that fail;
    among the passing, by `perturbation` (their flip counts are a handful of events, too few to compare), among the
    failing by `excess` (their failures are large enough to read: three quarters of the detections changed against
    a tenth)."""
    if accuracy_ok(report):
        return (0, perturbation(report), excess(report))
    return (1, excess(report), perturbation(report))


def accuracy_ok(report: GateReport) -> bool:
    """Whether every check that compares outputs passes (the evidence counts aside: a short gate has too few
    windows to be a verdict, only a pointer to the full gate)."""
    return all(ok for _, check, _, _, ok in report.checks() if not check.endswith("(at least)"))


def failing(report: GateReport) -> str:
    """The checks a report fails, as "check value (limit L)", comma-separated."""
    return ", ".join(
        f"{source} {check} {value:.3g} (limit {limit:g})"
        for source, check, value, limit, ok in report.checks()
        if not ok and not check.endswith("(at least)")
    )


def _trail_entry(report: GateReport, islands: tuple[str, ...], size: str) -> dict[str, object]:
    return {
        "islands": list(islands),
        "gate": size,
        "pass": report.ok,
        "accuracy_ok": accuracy_ok(report),
        "excess": round(excess(report), 3),
        "perturbation": round(perturbation(report), 3),
        "figures": report.figures(),
    }


def search_islands(
    onnx_path: str | Path,
    plain: GateReport,
    options: GateOptions,
    radiate: str | Path | None,
    log: Callable[[str], None] = print,
    gate: IslandsGate | None = None,
) -> GateReport:
    """The report to record for bf16 after plain bf16 failed (`plain`): the first islands set that passes, its
    folder moved beside the model, or `plain` with the search's trail when none passes."""
    import onnx

    onnx_path = Path(onnx_path)
    judge = gate or _gate_islands(options)
    matrix_free, matrix = search_units(onnx.load(str(onnx_path), load_external_data=False))
    order = matrix_free + matrix  # every set written in one order

    def ordered(units: set[str]) -> tuple[str, ...]:
        return tuple(u for u in order if u in units)

    def short_gate(islands: tuple[str, ...]) -> GateReport:
        folder = write_islands(onnx_path, islands, work / "short")
        report = judge(onnx_path, folder, options.search_sequences, options.search_frames, SEARCH_SEED, None)
        trail.append(_trail_entry(report, islands, "short"))
        log(
            f"islands search: {', '.join(islands)} in float32: short gate perturbation {perturbation(report):.3g}, "
            f"excess {excess(report):.3g}"
        )
        return report

    trail = [_trail_entry(plain, (), "full")]
    work = Path(tempfile.mkdtemp(dir=onnx_path.parent, prefix=f".{onnx_path.name}.islands-"))
    try:
        chosen = ordered(set(matrix_free))
        short = short_gate(chosen) if matrix_free else None
        while True:
            if short is not None and accuracy_ok(short):
                folder = write_islands(onnx_path, chosen, work / "full")
                report = judge(onnx_path, folder, options.sequences, options.frames, options.seed, radiate)
                trail.append(_trail_entry(report, chosen, "full"))
                verdict = "PASS" if report.ok else f"FAIL ({failing(report)})"
                log(f"islands search: {', '.join(chosen)} in float32: full gate {verdict}")
                if report.ok:
                    target = islands_dir(onnx_path)
                    replace_dir(folder, target)
                    report.islands, report.islands_sha256 = chosen, islands_sha256(target)
                    report.search = trail
                    for line in report.lines():
                        log(line)
                    return report
            remaining = [u for u in matrix if u not in chosen]
            if len(remaining) <= 1:
                break  # the last matrix unit in float32 too would leave no bf16
            tried = []
            for k, unit in enumerate(remaining):
                islands = ordered({*chosen, unit})
                report = short_gate(islands)
                tried.append((rank(report), k, islands, report))
            *_, chosen, short = min(tried, key=lambda t: t[:2])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log("islands search: no set of float32 islands short of all the matrix work passed; bf16 stays failed")
    return dataclasses.replace(plain, search=trail)


def _gate_islands(options: GateOptions) -> IslandsGate:
    def judge(
        onnx_path: Path, folder: Path, sequences: int, frames: int, seed: int, radiate: str | Path | None
    ) -> GateReport:
        return gate_model(
            onnx_path,
            ("openvino", "bf16"),
            sequences,
            frames,
            seed,
            radiate,
            options.threads,
            options.thresholds,
            islands=folder,
        )

    return judge
