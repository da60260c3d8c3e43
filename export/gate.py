"""Accuracy gate for reduced precision: a candidate runner (e.g. OpenVINO bf16) against onnxruntime fp32.

Not an element-wise tolerance: what a user of the detector would notice, on data the model never saw.
  - simulated held-out sequences (rafd.sim, a seed the model was not trained on, benchmark protocol via
    rafd.data.RadarWindowDataset), scored against their labels: mAP@0.3/0.5/0.7 and flow EPE (newest pair,
    pooled over the cells with a defined target, like rafd-eval);
  - the real RADIATE sample's frames (images only; poses by radar odometry): no labels, so only the
    comparisons with the reference.
Both runners stream the same frames (rafd.runtime, warm-up included); a sequence's first T-1 frames only fill
the caches, every later frame is one full window.

Detections above the score threshold are matched greedily (reference best first) to the nearest unused
candidate detection above the threshold within one feature cell; a detection without a partner on either
side has "changed". Checks (GateThresholds), on all compared frames together (the real sample alone is too
small for a 2% or p99 figure: one changed detection of its ~50 is 2%; its own figures are reported too):
changed / reference detections, p99 centre shift and p99 |score difference| of matched pairs; on the labelled
(simulated) frames: |mAP difference| at each IoU and |flow EPE difference|. And the evidence itself: fewer than
GATE_MIN_FRAMES compared windows or GATE_MIN_REFERENCE_DETECTIONS reference detections (rafd.protocol) is a FAIL
("too little to judge"), never a PASS: a gate that compared nothing has shown nothing.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from export.quantize import CALIBRATION_FRAMES, CALIBRATION_SEQUENCES
from rafd.config import RaFDConfig
from rafd.detections import decode_detections
from rafd.model_files import int8_model_path, islands_dir
from rafd.progress import bar
from rafd.protocol import (
    DEFAULT_SCORE_THRESHOLD,
    GATE_MIN_FRAMES,
    GATE_MIN_REFERENCE_DETECTIONS,
    IOU_THRESHOLDS,
    warming_up,
)
from rafd.runtime import StepResult, StreamRunner

DEFAULT_SEED = 7100  # not a seed of rafd bench accuracy's data (1000 train, 2000 test); override if a model saw it


@dataclass(frozen=True)
class GateThresholds:
    score_threshold: float = DEFAULT_SCORE_THRESHOLD  # detections compared are those at or above it
    changed_fraction: float = 0.02  # of the reference's detections
    centre_p99_m: float = 0.05
    score_p99: float = 0.02
    map_points: float = 0.5  # per IoU threshold, in mAP points (percent)
    epe_m: float = 0.01
    # the evidence needed before the gate judges at all (all sources together); lower only in tests of the checks
    min_frames: int = GATE_MIN_FRAMES
    min_reference_detections: int = GATE_MIN_REFERENCE_DETECTIONS


@dataclass
class SourceFigures:
    """What one source (simulated / radiate) gave; labels-based figures are None without labels."""

    frames: int = 0
    reference_detections: int = 0
    candidate_detections: int = 0
    changed: int = 0
    centre_shifts: list[float] = field(default_factory=list)
    score_differences: list[float] = field(default_factory=list)
    flow_differences: list[np.ndarray] = field(default_factory=list)  # per frame, |V_ref - V_cand| per cell
    reference_map: dict[float, float] | None = None
    candidate_map: dict[float, float] | None = None
    reference_epe: float | None = None
    candidate_epe: float | None = None

    @property
    def changed_fraction(self) -> float:
        return self.changed / max(1, self.reference_detections)

    @property
    def centre_p99(self) -> float:
        return float(np.percentile(self.centre_shifts, 99)) if self.centre_shifts else 0.0

    @property
    def score_p99(self) -> float:
        return float(np.percentile(self.score_differences, 99)) if self.score_differences else 0.0

    def flow_difference(self, q: float | None = None) -> float:
        """Mean (q None) or q-th percentile over cells of |flow_ref - flow_cand| (m)."""
        if not self.flow_differences:
            return 0.0
        values = np.concatenate(self.flow_differences)
        return float(values.mean() if q is None else np.percentile(values, q))


@dataclass
class GateReport:
    reference: str  # "onnxruntime/fp32"
    candidate: str  # e.g. "openvino/bf16"
    thresholds: GateThresholds
    sources: dict[str, SourceFigures]
    # int8: the sha256 of the quantized file judged (MODEL.int8.onnx); the service serves that file only
    judged_sha256: str | None = None
    # float32 islands (export/islands_gate.py): the units kept in float32, () for the plain precision; bf16's also
    # the sha256 of the segments' folder judged (rafd.model_files.islands_sha256)
    islands: tuple[str, ...] = ()
    islands_sha256: str | None = None
    # the islands search that led here: one entry per gate it ran (islands, gate size, verdict, excess)
    search: list[dict[str, Any]] = field(default_factory=list)

    @property
    def pooled(self) -> SourceFigures:
        """The detection comparisons of every source together."""
        pooled = SourceFigures()
        for s in self.sources.values():
            pooled.frames += s.frames
            pooled.reference_detections += s.reference_detections
            pooled.candidate_detections += s.candidate_detections
            pooled.changed += s.changed
            pooled.centre_shifts += s.centre_shifts
            pooled.score_differences += s.score_differences
            pooled.flow_differences += s.flow_differences
        return pooled

    def checks(self) -> list[tuple[str, str, float, float, bool]]:
        """(source, check, value, limit, ok) for every gated figure."""
        t, all_frames = self.thresholds, self.pooled
        out = [
            (
                "all",
                "compared windows (at least)",
                float(all_frames.frames),
                float(t.min_frames),
                all_frames.frames >= t.min_frames,
            ),
            (
                "all",
                "reference detections (at least)",
                float(all_frames.reference_detections),
                float(t.min_reference_detections),
                all_frames.reference_detections >= t.min_reference_detections,
            ),
            (
                "all",
                "changed detections (fraction)",
                all_frames.changed_fraction,
                t.changed_fraction,
                all_frames.changed_fraction <= t.changed_fraction,
            ),
            (
                "all",
                "matched centre shift p99 (m)",
                all_frames.centre_p99,
                t.centre_p99_m,
                all_frames.centre_p99 <= t.centre_p99_m,
            ),
            (
                "all",
                "matched score difference p99",
                all_frames.score_p99,
                t.score_p99,
                all_frames.score_p99 <= t.score_p99,
            ),
        ]
        for name, s in self.sources.items():
            if s.reference_map is not None and s.candidate_map is not None:
                for iou in IOU_THRESHOLDS:
                    delta = abs(s.candidate_map[iou] - s.reference_map[iou])
                    out.append((name, f"|mAP@{iou:g} difference| (points)", delta, t.map_points, delta <= t.map_points))
            if s.reference_epe is not None and s.candidate_epe is not None:
                delta = abs(s.candidate_epe - s.reference_epe)
                out.append((name, "|flow EPE difference| (m)", delta, t.epe_m, delta <= t.epe_m))
        return out

    @property
    def ok(self) -> bool:
        return all(check[-1] for check in self.checks())

    def figures(self) -> dict[str, dict[str, float]]:
        """Flat figures per source and for all sources together (for JSON, rafd-bench and the ONNX metadata)."""
        out: dict[str, dict[str, float]] = {}
        sources = dict(self.sources, all=self.pooled) if len(self.sources) > 1 else self.sources
        for name, s in sources.items():
            row = {
                "frames": s.frames,
                "reference_detections": s.reference_detections,
                "candidate_detections": s.candidate_detections,
                "changed_fraction": round(s.changed_fraction, 4),
                "centre_p99_m": round(s.centre_p99, 4),
                "score_p99": round(s.score_p99, 4),
                "flow_mean_difference_m": round(s.flow_difference(), 4),
                "flow_p99_difference_m": round(s.flow_difference(99), 4),
            }
            if s.reference_map is not None and s.candidate_map is not None:
                for iou in IOU_THRESHOLDS:
                    row[f"reference_mAP@{iou:g}"] = round(s.reference_map[iou], 2)
                    row[f"candidate_mAP@{iou:g}"] = round(s.candidate_map[iou], 2)
            if s.reference_epe is not None and s.candidate_epe is not None:
                row["reference_epe_m"] = round(s.reference_epe, 4)
                row["candidate_epe_m"] = round(s.candidate_epe, 4)
            out[name] = row
        return out

    def too_little(self) -> str | None:
        """Why the gate refused to judge (too few windows or detections), or None."""
        short = [
            f"{check.removesuffix(' (at least)')} {value:g} < {limit:g}"
            for _, check, value, limit, ok in self.checks()[:2]
            if not ok
        ]
        return "too little to judge: " + ", ".join(short) if short else None

    def lines(self) -> list[str]:
        verdict = "PASS" if self.ok else "FAIL"
        reason = self.too_little()
        islands = f" with float32 islands {', '.join(self.islands)}" if self.islands else ""
        out = [
            f"accuracy gate {self.candidate}{islands} vs {self.reference}: {verdict}"
            + (f" ({reason})" if reason else "")
        ]
        for name, figures in self.figures().items():
            out.append(f"  {name}: " + ", ".join(f"{k} {v}" for k, v in figures.items()))
        for source, check, value, limit, ok in self.checks():
            out.append(f"  {'ok  ' if ok else 'FAIL'} {source:9s} {check:34s} {value:.4g} (limit {limit:g})")
        return out


# ----------------------------------------------------------------------------- comparing two results
def compare_frame(
    figures: SourceFigures, reference: StepResult, candidate: StepResult, cfg: RaFDConfig, score_threshold: float
) -> None:
    """Add one frame's detection and flow comparison to `figures`."""
    figures.frames += 1
    ref = decode_detections(reference.boxes, reference.scores, score_threshold)
    cand = decode_detections(candidate.boxes, candidate.scores, score_threshold)
    figures.reference_detections += len(ref.scores)
    figures.candidate_detections += len(cand.scores)
    used = np.zeros(len(cand.scores), bool)
    for i in range(len(ref.scores)):  # best reference detection first (decode_detections sorts)
        distance = np.linalg.norm(cand.boxes[:, :2] - ref.boxes[i, :2], axis=1)
        distance[used] = np.inf
        j = int(np.argmin(distance)) if len(distance) else -1
        if j < 0 or distance[j] > cfg.cell_size:
            figures.changed += 1
            continue
        used[j] = True
        figures.centre_shifts.append(float(distance[j]))
        figures.score_differences.append(float(abs(ref.scores[i] - cand.scores[j])))
    figures.changed += int((~used).sum())
    if reference.flow is not None and candidate.flow is not None:
        newest = np.linalg.norm(reference.flow[-1] - candidate.flow[-1], axis=0)  # [Hf, Wf] metres
        figures.flow_differences.append(newest.ravel())


# ----------------------------------------------------------------------------- sources
@dataclass
class LabelledFrame:
    frame: np.ndarray  # float32 [S, S] model input
    pose: np.ndarray  # float64 [3] world pose
    boxes: np.ndarray | None = None  # [M, 5] protocol GT of this frame (None: no labels or warm-up frame)
    gt_flow: np.ndarray | None = None  # [2, Hf, Wf] pseudo-GT flow of the newest pair
    flow_valid: np.ndarray | None = None  # [Hf, Wf] cells with a defined flow target


def simulated_sequences(cfg: RaFDConfig, sequences: int, frames: int, seed: int) -> Iterator[list[LabelledFrame]]:
    """Simulate held-out sequences (rafd.sim, scans of max(256, S) px) and yield each one's frames in order,
    labelled under the benchmark protocol from frame T on (earlier frames only warm the stream up)."""
    from rafd.data.dataset import RadarWindowDataset
    from rafd.data.targets import build_targets
    from rafd.preprocess import to_model_input
    from rafd.sim.api import simulate_dataset

    with tempfile.TemporaryDirectory(prefix="rafd-gate-") as tmp:
        simulate_dataset(tmp, sequences, frames, seed, split="test", size=max(256, cfg.input_size))
        dataset = RadarWindowDataset(tmp, split="test", cfg=cfg)
        current: list[LabelledFrame] = []
        previous_key = None
        for index in range(len(dataset)):
            window = dataset.window(index)
            key = (window["sequence"], window["frame"])
            if previous_key is None or key[0] != previous_key[0] or key[1] != previous_key[1] + 1:
                if current:
                    yield current
                # a new stream: the window's older frames first (unlabelled warm-up)
                current = [
                    LabelledFrame(to_model_input(f), p) for f, p in zip(window["frames"][:-1], window["poses"][:-1])
                ]
            previous_key = key
            targets = build_targets(window["boxes"], window["ids"], window["poses"], cfg)
            current.append(
                LabelledFrame(
                    to_model_input(window["frames"][-1]),
                    window["poses"][-1],
                    np.asarray(window["boxes"][-1]).reshape(-1, 5),
                    targets["flow"][-1] if len(targets["flow"]) else None,
                    targets["flow_valid"][-1, 0] if len(targets["flow_valid"]) else None,
                )
            )
        if current:
            yield current


def radiate_frames(folder: str | Path, cfg: RaFDConfig, length: int = 1000) -> list[LabelledFrame]:
    """A real RADIATE sequence's frames (images only, poses by odometry), unlabelled."""
    from export.verify import radiate_sequence

    frames, poses = radiate_sequence(folder, cfg, length)
    return [LabelledFrame(f, p) for f, p in zip(frames, poses)]


# ----------------------------------------------------------------------------- the gate
def run_sequence(
    reference: StreamRunner,
    candidate: StreamRunner,
    frames: list[LabelledFrame],
    figures: SourceFigures,
    thresholds: GateThresholds,
    labelled: dict[str, list[Any]],
    advance: Callable[[], object] = lambda: None,
) -> None:
    """Stream one sequence through both runners; compare every full window; collect labelled outputs."""
    from rafd.eval.metrics import end_point_error_terms

    states = [reference.new_state(), candidate.new_state()]
    for item in frames:
        ref, states[0] = reference.step(states[0], item.frame, item.pose)
        cand, states[1] = candidate.step(states[1], item.frame, item.pose)
        advance()
        if warming_up(ref.frames_used, reference.config.num_frames):
            continue  # the window is padded
        compare_frame(figures, ref, cand, reference.config, thresholds.score_threshold)
        if item.boxes is not None:
            labelled["gt"].append(item.boxes)
            for name, result in (("reference", ref), ("candidate", cand)):
                labelled[name].append(decode_detections(result.boxes, result.scores, 0.0).as_array())
                if item.gt_flow is not None and item.flow_valid is not None and result.flow is not None:
                    labelled[f"{name}_epe"].append(
                        end_point_error_terms(result.flow[-1], item.gt_flow, item.flow_valid[None])
                    )


def run_gate(
    reference: StreamRunner,
    candidate: StreamRunner,
    sources: dict[str, Iterator[list[LabelledFrame]]],
    thresholds: GateThresholds = GateThresholds(),
    log: Callable[[str], None] = lambda _: None,
    expected_frames: dict[str, int] | None = None,
) -> GateReport:
    """sources: name -> sequences of frames (labelled or not); `expected_frames`: name -> frames, for the progress
    bar's estimate. Returns the report (check .ok)."""
    from rafd.eval.metrics import mean_average_precision

    if reference.config != candidate.config:
        raise ValueError("the reference and the candidate run different models")
    report = GateReport(
        f"{reference.runtime}/{reference.precision}", f"{candidate.runtime}/{candidate.precision}", thresholds, {}
    )
    for name, sequences in sources.items():
        figures = SourceFigures()
        labelled: dict[str, list[Any]] = {  # GT and detection arrays, (sum, count) EPE terms
            "gt": [],
            "reference": [],
            "candidate": [],
            "reference_epe": [],
            "candidate_epe": [],
        }
        total = (expected_frames or {}).get(name)
        with bar(desc=f"gate {report.candidate}: {name} frames", total=total, unit="frame") as progress:
            for frames in sequences:
                run_sequence(reference, candidate, frames, figures, thresholds, labelled, progress.update)
        if labelled["gt"]:
            for side in ("reference", "candidate"):
                aps = mean_average_precision(labelled[side], labelled["gt"], IOU_THRESHOLDS)
                setattr(figures, f"{side}_map", {iou: 100.0 * float(aps[iou]) for iou in IOU_THRESHOLDS})
                terms = labelled[f"{side}_epe"]
                cells = sum(c for _, c in terms)
                setattr(figures, f"{side}_epe", sum(s for s, _ in terms) / cells if cells else math.nan)
        report.sources[name] = figures
        log(f"gate source {name}: {figures.frames} frames compared")
    return report


def gate_model(
    onnx_path: str | Path,
    candidate: tuple[str, str] = ("openvino", "bf16"),
    sequences: int = 12,
    frames: int = 60,
    seed: int = DEFAULT_SEED,
    radiate: str | Path | None = None,
    threads: int | None = None,
    thresholds: GateThresholds = GateThresholds(),
    log: Callable[[str], None] = lambda _: None,
    islands: str | Path | None = None,
    quantized: str | Path | None = None,
    drives: dict[tuple[int, int, int], list[list[LabelledFrame]]] | None = None,
) -> GateReport:
    """The gate of one exported step graph: onnxruntime fp32 vs `candidate` (runtime, precision). bf16 is judged
    plain, or as the segments of the bf16-islands folder `islands` (export/islands.py) when given; int8 as
    MODEL.int8.onnx beside the model, or the quantized model `quantized` when given. `drives`: simulated drives kept
    by (sequences, frames, seed), read from and added to (a search gating many candidates on the same drives)."""
    from rafd.runtime import OnnxRunner, OpenVinoRunner, open_runner

    reference = OnnxRunner(onnx_path, threads)
    if islands is not None:
        other: StreamRunner = OpenVinoRunner(onnx_path, "bf16", threads, islands=islands)
    elif quantized is not None:
        other = OpenVinoRunner(onnx_path, "int8", threads, quantized=quantized)
    else:
        other = open_runner(onnx_path, *candidate, threads, islands=False)
    if reference.form != "step":
        raise ValueError(f"the gate streams the step form; {onnx_path} is a {reference.form!r} graph")
    key = (sequences, frames, seed)
    if drives is None:
        simulated = simulated_sequences(reference.config, *key)
    else:
        if key not in drives:
            drives[key] = list(simulated_sequences(reference.config, *key))
        simulated = iter(drives[key])
    sources: dict[str, Iterator[list[LabelledFrame]]] = {"simulated": simulated}
    expected = {"simulated": sequences * frames}
    if radiate is not None:
        real = radiate_frames(radiate, reference.config)
        sources["radiate"] = iter([real])
        expected["radiate"] = len(real)
    return run_gate(reference, other, sources, thresholds, log, expected)


# ----------------------------------------------------------------------------- rafd-export --gate
@dataclass(frozen=True)
class GateOptions:
    # ~700 compared windows: with fewer, bf16's flips of single boxes across IoU 0.7 move mAP by a point or more
    # either way (measured on the shipped model: 222 windows gave mAP@0.5/0.7 differences of 1.4 / 1.3 points,
    # 684 windows 0.0 / 0.5)
    sequences: int = 12
    frames: int = 60
    seed: int = DEFAULT_SEED
    threads: int | None = None
    thresholds: GateThresholds = GateThresholds()
    # where plain bf16 or int8 fails: search for float32 islands that pass (export/islands_gate.py), trying each unit
    # on a short gate of search_sequences x search_frames (other simulated drives than the gate's)
    islands: bool = True
    search_sequences: int = 2
    search_frames: int = 40
    # int8's activation statistics: simulated sequences of their own seed (export.quantize.CALIBRATION_SEED)
    calibration_sequences: int = CALIBRATION_SEQUENCES
    calibration_frames: int = CALIBRATION_FRAMES


def run_export_gates(
    onnx_path: str | Path, options: GateOptions, log: Callable[[str], None] = print
) -> dict[str, GateReport]:
    """The gate of every reduced precision this machine runs (OpenVINO bf16 where the CPU has it); the real
    sample's frames join when RAFD_RADIATE_SAMPLE names a RADIATE sequence."""
    from rafd.runtime import supported_choices

    reduced = [(runtime, precision) for runtime, precision in supported_choices() if precision != "fp32"]
    if not reduced:
        log(
            "accuracy gate: this CPU runs no reduced precision (bf16 needs openvino and avx512_bf16 or AMX, int8 "
            "VNNI or AMX); nothing to gate"
        )
        return {}
    sample = os.environ.get("RAFD_RADIATE_SAMPLE")
    radiate = sample if sample and Path(sample, "Navtech_Cartesian").is_dir() else None
    return {candidate[1]: _gate_precision(onnx_path, candidate, options, radiate, log) for candidate in reduced}


def _gate_precision(
    onnx_path: str | Path,
    candidate: tuple[str, str],
    options: GateOptions,
    radiate: str | None,
    log: Callable[[str], None],
) -> GateReport:
    """One reduced precision's gate, with its islands search where the plain precision fails on enough evidence."""
    calibration = None  # int8's: made once, for the plain model and every islands set
    if candidate[1] == "int8":  # its own model: quantized (again) here, every matrix operation, then judged
        from export.quantize import calibrate, quantize_model

        calibration = calibrate(onnx_path, options.calibration_sequences, options.calibration_frames, log=log)
        quantized = quantize_model(onnx_path, calibration=calibration)
        log(f"int8: wrote {quantized}")
    report = gate_model(
        onnx_path,
        candidate,
        options.sequences,
        options.frames,
        options.seed,
        radiate,
        options.threads,
        options.thresholds,
        log,
    )
    if candidate[1] == "int8":
        from rafd.model_files import file_sha256

        report.judged_sha256 = file_sha256(quantized)
    for line in report.lines():
        log(line)
    if not report.ok and report.too_little() is None and options.islands:
        from export.islands_gate import search_islands

        report = search_islands(
            onnx_path, report, options, radiate, log, precision=candidate[1], calibration=calibration
        )
    return report


def gate_metadata(reports: dict[str, GateReport]) -> dict[str, str]:
    """ONNX metadata entries for the gate verdicts (rafd.runtime.runners.GATE_KEY). The figures also say on which
    CPU and when the gate ran: a verdict on another CPU's bf16 kernels is evidence, not proof, for this one's."""
    import datetime

    from rafd import __version__
    from rafd.cpu import cpu_model_and_flags

    cpu, cpu_flags = cpu_model_and_flags()
    units = [f for f in ("avx512_bf16", "amx_bf16", "amx_int8", "avx512_vnni") if f in cpu_flags]
    made = {
        "cpu": f"{cpu} ({', '.join(units) or 'no bf16 or int8 units'})",
        "date": datetime.date.today().isoformat(),
        "rafd_version": __version__,
    }
    out = {}
    for precision, report in reports.items():
        out[f"gate_{precision}"] = "pass" if report.ok else "fail"
        judged: dict[str, Any] = {"int8_sha256": report.judged_sha256} if report.judged_sha256 else {}
        if report.islands:
            judged["islands"] = list(report.islands)
        if report.islands_sha256:
            judged["islands_sha256"] = report.islands_sha256
        if report.search:
            judged["islands_search"] = report.search
        out[f"gate_{precision}_figures"] = json.dumps(
            {
                "candidate": report.candidate,
                "reference": report.reference,
                "figures": report.figures(),
                **made,
                **judged,
            },
            sort_keys=True,
        )
    return out


def record_gates(onnx_path: str | Path, reports: dict[str, GateReport]) -> dict[str, str]:
    """Write the gate verdicts into an existing ONNX model's metadata, in place, without re-exporting: the graph and
    every other metadata entry are kept; a precision's earlier record is replaced, other precisions' records are kept.
    Atomic (a temporary file beside the model, then a rename). Returns the entries written."""
    import onnx

    path = Path(onnx_path)
    entries = gate_metadata(reports)
    proto = onnx.load(str(path))
    kept = [(p.key, p.value) for p in proto.metadata_props if p.key not in entries]
    del proto.metadata_props[:]
    for key, value in [*kept, *entries.items()]:
        proto.metadata_props.add(key=key, value=value)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        onnx.save(proto, str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return entries


def put_in_place(model: Path, target: Path) -> None:
    """Move `model` and the judged files beside it (MODEL.int8.onnx, MODEL.bf16-islands/) to `target`'s names (one
    file system): the files first, the model, whose records name them, last."""
    from export.islands import replace_dir

    if int8_model_path(model).is_file():
        os.replace(int8_model_path(model), int8_model_path(target))
    if islands_dir(model).is_dir():
        replace_dir(islands_dir(model), islands_dir(target))
    os.replace(model, target)


def gate_and_record(
    onnx_path: str | Path, options: GateOptions, out: str | Path | None = None, log: Callable[[str], None] = print
) -> dict[str, GateReport]:
    """`rafd gate`: run the gates of an existing model and record them, in place or to `out`. Everything runs on a
    copy in a folder beside the target, the model's judged files with it (MODEL.int8.onnx, MODEL.bf16-islands/,
    which a gate quantizes or writes anew): only once every gate has finished do they and the recorded model take
    their places, so an interrupted gate leaves what was stored as it was, and with `out` the input and its files
    are never written."""
    source = Path(onnx_path)
    target = Path(out) if out is not None else source
    work = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.gate-"))
    try:
        model = work / target.name
        shutil.copyfile(source, model)
        # the files of the records a gate here does not replace (a precision this CPU lacks) go with them
        if int8_model_path(source).is_file():
            shutil.copyfile(int8_model_path(source), int8_model_path(model))
        if islands_dir(source).is_dir():
            shutil.copytree(islands_dir(source), islands_dir(model))
        reports = run_export_gates(model, options, log)
        if reports:
            record_gates(model, reports)
            put_in_place(model, target)
        return reports
    finally:
        shutil.rmtree(work, ignore_errors=True)
