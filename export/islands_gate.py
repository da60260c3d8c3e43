"""Choosing float32 islands by measurement, where plain reduced precision fails its accuracy gate: bf16 with float32
islands (its graph cut into segments, export/islands.py) and int8 with float32 islands (its matrix operations in the
islands left unquantized, export/quantize.py).

The candidates are the graph's units (export/islands.search_units): bf16's are each module two levels down
("/flow/match/") and each scope's own nodes ("/propagation/*"); int8's one level deeper ("/encoder/backbone/stem/"),
since its error gathers in single layers (on the shipped model the backbone's first convolution, which reads the
radar image, moved the matched centres more than the rest of the backbone together). bf16's units without a matrix
operation are float32 from the start: bf16 speeds up nothing there, and they hold the poses, the sampling positions,
GridSample and the decode's top-k, where its rounding moves things most (int8 quantizes matrix operations only, so
they are never int8). Every gate is first a short one, on simulated drives apart from the gate's (SEARCH_SEED), and
its figures rank the candidates (`rank`: those whose accuracy checks pass first, by how far they move the matched
detections, `perturbation`, since a short gate's flip counts are a handful of events; the rest by how far they are
over the limits, `excess`); a set whose short gate passes its accuracy checks is judged by the full gate (the same
as the plain precision's), and the first set the full gate passes is kept.

bf16 grows its islands by greedy forward selection (_by_forward_selection): from the matrix-free units, at each step
every matrix unit not yet chosen is tried, added to the islands so far, and the best joins. int8 ranks its units by
sensitivity first (_by_sensitivity): each quantized alone, then quantized in that order, least sensitive first, as
long as the short gate holds. Either keeps as much of the graph's matrix work in the reduced precision as passes,
among the sets it tries; every matrix unit in float32 is no reduced precision at all, so neither goes that far. The
passing set's files stay beside the model (bf16: MODEL.bf16-islands/; int8: MODEL.int8.onnx) and its record names the
islands and the files' digest (GateReport.islands, islands_sha256 / judged_sha256); every gate the search ran is in
the record too (GateReport.search).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from export.gate_drives import LabelledFrame
from export.gate_options import GateOptions
from export.gate_report import GateReport
from export.gate_run import gate_model
from export.islands import replace_dir, search_units, write_islands
from export.quantize import Calibration
from rafd.model_files import file_sha256, int8_model_path, islands_dir, islands_sha256

SEARCH_SEED = 7200  # apart from the gate's (export.gate_options.DEFAULT_SEED), int8 calibration's and training's
NOT_FINITE = 1e6  # the excess of a check whose figure is not finite (the arithmetic broke)

INT8_UNIT_DEPTH = 3  # int8's units: one level below bf16's (the module docstring says why)

# (onnx_path, candidate, sequences, frames, seed, radiate) -> report: the gate of one islands set, its candidate a
# bf16-islands folder or an int8 model
IslandsGate = Callable[[Path, Path, int, int, int, "str | Path | None"], GateReport]


class Bf16Islands:
    """bf16's islands: the graph cut into segments (export/islands.py), the matrix-free units float32 from the
    start."""

    precision = "bf16"

    def __init__(self, onnx_path: Path) -> None:
        self.onnx_path = onnx_path

    def units(self, proto: Any) -> tuple[list[str], list[str]]:
        """(float32 from the start, the matrix units the search chooses among)."""
        return search_units(proto)

    def write(self, islands: tuple[str, ...], where: Path) -> Path:
        return write_islands(self.onnx_path, islands, where)

    def keep(self, candidate: Path, report: GateReport) -> None:
        """Put the passing candidate beside the model and name it in the report."""
        target = islands_dir(self.onnx_path)
        replace_dir(candidate, target)
        report.islands_sha256 = islands_sha256(target)


class Int8Islands:
    """int8's islands: the matrix operations in them left unquantized (export/quantize.py), from one calibration for
    every set the search tries (made here unless given)."""

    precision = "int8"

    def __init__(self, onnx_path: Path, calibration: Calibration | None = None) -> None:
        self.onnx_path = onnx_path
        self.calibration = calibration

    def units(self, proto: Any) -> tuple[list[str], list[str]]:
        return [], search_units(proto, INT8_UNIT_DEPTH)[1]

    def write(self, islands: tuple[str, ...], where: Path) -> Path:
        from export.quantize import calibrate, quantize_model

        if self.calibration is None:
            self.calibration = calibrate(self.onnx_path)
        return quantize_model(self.onnx_path, where.with_suffix(".int8.onnx"), islands, self.calibration)

    def keep(self, candidate: Path, report: GateReport) -> None:
        target = int8_model_path(self.onnx_path)
        os.replace(candidate, target)
        report.judged_sha256 = file_sha256(target)


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


class _Search:
    """One search's gates: the short gate of a set (SEARCH_SEED's drives) and the full one (the gate's), each
    candidate written into the search's folder, every gate logged and kept in the trail."""

    def __init__(
        self,
        onnx_path: Path,
        form: Bf16Islands | Int8Islands,
        judge: IslandsGate,
        options: GateOptions,
        radiate: str | Path | None,
        log: Callable[[str], None],
        work: Path,
        order: list[str],
    ) -> None:
        self.onnx_path, self.form, self.judge, self.options = onnx_path, form, judge, options
        self.radiate, self.log, self.work, self.order = radiate, log, work, order
        self.trail: list[dict[str, object]] = []

    def ordered(self, units: set[str] | list[str]) -> tuple[str, ...]:
        """A set of units in one order (the graph's): every set is written alike."""
        return tuple(u for u in self.order if u in units)

    def short(self, islands: tuple[str, ...]) -> GateReport:
        candidate = self.form.write(islands, self.work / "short")
        sequences, frames = self.options.search_sequences, self.options.search_frames
        report = self.judge(self.onnx_path, candidate, sequences, frames, SEARCH_SEED, None)
        self.trail.append(_trail_entry(report, islands, "short"))
        self.log(
            f"{self.form.precision} islands search: {', '.join(islands)} in float32: short gate perturbation "
            f"{perturbation(report):.3g}, excess {excess(report):.3g}"
        )
        return report

    def full(self, islands: tuple[str, ...]) -> GateReport:
        """The full gate of a set; its candidate is kept beside the model when it passes."""
        candidate = self.form.write(islands, self.work / "full")
        options = self.options
        report = self.judge(self.onnx_path, candidate, options.sequences, options.frames, options.seed, self.radiate)
        self.trail.append(_trail_entry(report, islands, "full"))
        verdict = "PASS" if report.ok else f"FAIL ({failing(report)})"
        self.log(f"{self.form.precision} islands search: {', '.join(islands)} in float32: full gate {verdict}")
        if report.ok:
            self.form.keep(candidate, report)
            report.islands = islands
        return report


def search_islands(
    onnx_path: str | Path,
    plain: GateReport,
    options: GateOptions,
    radiate: str | Path | None,
    log: Callable[[str], None] = print,
    gate: IslandsGate | None = None,
    precision: str = "bf16",
    calibration: Calibration | None = None,
) -> GateReport:
    """The report to record for `precision` ("bf16" or "int8") after its plain form failed (`plain`): the first
    islands set that passes, its files moved beside the model, or `plain` with the search's trail when none passes.
    `calibration`: int8's (export.quantize.calibrate), when the caller has made it already."""
    import onnx

    onnx_path = Path(onnx_path)
    form: Bf16Islands | Int8Islands = (
        Int8Islands(onnx_path, calibration) if precision == "int8" else Bf16Islands(onnx_path)
    )
    start, matrix = form.units(onnx.load(str(onnx_path), load_external_data=False))
    work = Path(tempfile.mkdtemp(dir=onnx_path.parent, prefix=f".{onnx_path.name}.islands-"))
    judge = gate or _gate_islands(options, precision)
    search = _Search(onnx_path, form, judge, options, radiate, log, work, start + matrix)
    search.trail.append(_trail_entry(plain, (), "full"))
    try:
        int8 = precision == "int8"
        passed = _by_sensitivity(search, matrix) if int8 else _by_forward_selection(search, start, matrix)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if passed is None:
        log(
            f"{precision} islands search: no set of float32 islands short of all the matrix work passed; "
            f"{precision} stays failed"
        )
        return dataclasses.replace(plain, search=search.trail)
    passed.search = search.trail
    for line in passed.lines():
        log(line)
    return passed


def _by_forward_selection(search: _Search, start: list[str], matrix: list[str]) -> GateReport | None:
    """bf16's search: the islands grow from `start` by greedy forward selection over the matrix units (the module
    docstring); the first set the full gate passes, or None."""
    chosen = search.ordered(start)
    short = search.short(chosen) if start else None
    while True:
        if short is not None and accuracy_ok(short):
            report = search.full(chosen)
            if report.ok:
                return report
        remaining = [u for u in matrix if u not in chosen]
        if len(remaining) <= 1:
            return None  # the last matrix unit in float32 too would leave no reduced precision
        tried = []
        for k, unit in enumerate(remaining):
            islands = search.ordered({*chosen, unit})
            report = search.short(islands)
            tried.append((rank(report), k, islands, report))
        *_, chosen, short = min(tried, key=lambda t: t[:2])


def _by_sensitivity(search: _Search, matrix: list[str]) -> GateReport | None:
    """int8's search, sensitivity first: each matrix unit quantized alone (a short gate each) ranks the units by
    how far int8 there moves the outputs (`rank`); then, least sensitive first, each unit is quantized on top of
    those kept while the short gate's accuracy checks still pass; the full gate judges the set, and while it fails
    the unit quantized last returns to float32. The first set the full gate passes, or None.

    Why not bf16's forward selection: int8's error is spread over many layers, each adding a little, so with every
    unit quantized no single unit returned to float32 brings a short gate near passing, and the greedy steps
    wander; the damage of a unit quantized alone separates the units cleanly."""
    alone = {u: search.short(search.ordered([v for v in matrix if v != u])) for u in matrix}
    order = sorted(matrix, key=lambda u: (rank(alone[u]), matrix.index(u)))
    quantized: list[str] = []
    for unit in order:
        report = alone[unit] if not quantized else search.short(search.ordered(set(matrix) - {*quantized, unit}))
        if accuracy_ok(report):
            quantized.append(unit)
    while quantized:
        report = search.full(search.ordered(set(matrix) - set(quantized)))
        if report.ok:
            return report
        quantized.pop()  # the most sensitive unit quantized returns to float32
    return None


def _gate_islands(options: GateOptions, precision: str) -> IslandsGate:
    # The short gates' drives are simulated once and kept for every candidate (a few dozen frames); the full gate's
    # are many more, simulated each time it runs.
    short_drives: dict[tuple[int, int, int], list[list[LabelledFrame]]] = {}

    def judge(
        onnx_path: Path, candidate: Path, sequences: int, frames: int, seed: int, radiate: str | Path | None
    ) -> GateReport:
        return gate_model(
            onnx_path,
            ("openvino", precision),
            sequences,
            frames,
            seed,
            radiate,
            options.threads,
            options.thresholds,
            islands=candidate if precision == "bf16" else None,
            quantized=candidate if precision == "int8" else None,
            drives=short_drives if seed == SEARCH_SEED else None,
        )

    return judge
