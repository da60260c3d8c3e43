"""One accuracy gate: a candidate runner (e.g. OpenVINO bf16) against onnxruntime fp32, not an element-wise
tolerance but what a user of the detector would notice, on data the model never saw (export.gate_drives).

Both runners stream the same frames (rafd.runtime, warm-up included); a sequence's first T-1 frames only fill the
caches, every later frame is one full window, compared (export.gate_report) and, where labelled, scored: mAP@0.3/
0.5/0.7 and flow EPE (newest pair, pooled over the cells with a defined target, like rafd eval).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from export.gate_drives import LabelledFrame, radiate_frames, simulated_sequences
from export.gate_options import DEFAULT_SEED, GateThresholds
from export.gate_report import GateReport, SourceFigures, compare_frame
from rafd.detections import decode_detections
from rafd.progress import bar
from rafd.protocol import IOU_THRESHOLDS, warming_up
from rafd.runtime import StreamRunner


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
        ref, states[0] = reference.step(states[0], item.frame[None], item.pose[None])
        cand, states[1] = candidate.step(states[1], item.frame[None], item.pose[None])
        ref, cand = ref.view(0), cand.view(0)
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
                        end_point_error_terms(result.flow, item.gt_flow, item.flow_valid[None])
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
