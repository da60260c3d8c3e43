"""What an accuracy gate measured and its verdict: each source's figures (SourceFigures), the checks against the
limits (GateReport), and one frame's comparison of the reference's and the candidate's answers (compare_frame).

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

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from export.gate_options import GateThresholds
from rafd.config import RaFDConfig
from rafd.detections import decode_detections
from rafd.protocol import IOU_THRESHOLDS
from rafd.runtime import StepResult


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
        """Flat figures per source and for all sources together (for JSON, rafd bench speed and the ONNX metadata)."""
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
        newest = np.linalg.norm(reference.flow - candidate.flow, axis=0)  # [Hf, Wf] metres
        figures.flow_differences.append(newest.ravel())
