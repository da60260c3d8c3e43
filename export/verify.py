"""Parity of an exported RaFD ONNX file (onnxruntime, CPU) with the PyTorch model.

Dense outputs (heatmap, flow) are compared element-wise (|ort - torch| <= atol + rtol * |torch|). The K detections
are compared as sets: top-K ties may come out in another order, so each ORT detection is matched to the unused
PyTorch detection of equal score (within tolerance) with the nearest centre. An ORT detection without a partner is
accepted only at the top-K boundary (its score equals the K-th PyTorch score within tolerance: the tie was broken
the other way).

The step graph is verified by streaming a sequence through rafd.runtime.OnnxRunner and comparing every frame, the
warm-up frames included, with model.forward on the warm-up-padded window (window_from_history); a graph with a free
batch axis also streams two views at once (the tiles of a whole scan step so).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from rafd.config import RaFDConfig
from rafd.geometry import relative_pose
from rafd.runtime import OnnxRunner, StreamRunner
from rafd.runtime.backend import DYNAMIC

# (rtol, atol) per output; heatmap and flow as issue 5 asks, boxes in metres / radians.
TOLERANCES: dict[str, tuple[float, float]] = {
    "heatmap": (1e-3, 1e-4),
    "flow": (1e-3, 1e-4),
    "scores": (1e-3, 1e-4),
    "boxes": (1e-3, 1e-4),
}


class VerificationError(RuntimeError):
    """The ONNX outputs differ from PyTorch beyond tolerance."""


@dataclass
class Diff:
    """Worst differences of one output over one or more comparisons."""

    max_abs: float = 0.0
    max_rel: float = 0.0  # |ort - torch| / max(|torch|, atol)
    worst: float = 0.0  # max |ort - torch| / (atol + rtol |torch|): <= 1 passes
    boundary_swaps: int = 0  # detections exchanged at the top-K boundary (equal scores)
    unmatched: int = 0  # detections without a partner (fails)

    @property
    def ok(self) -> bool:
        return self.worst <= 1.0 and self.unmatched == 0

    def update(self, other: Diff) -> None:
        self.max_abs = max(self.max_abs, other.max_abs)
        self.max_rel = max(self.max_rel, other.max_rel)
        self.worst = max(self.worst, other.worst)
        self.boundary_swaps += other.boundary_swaps
        self.unmatched += other.unmatched


@dataclass
class Report:
    """Per source ("random", "radiate") and output, the worst differences; `cases` = compared windows."""

    diffs: dict[str, dict[str, Diff]] = field(default_factory=dict)
    cases: dict[str, int] = field(default_factory=dict)

    def add(self, source: str, name: str, diff: Diff) -> None:
        self.diffs.setdefault(source, {}).setdefault(name, Diff()).update(diff)

    @property
    def ok(self) -> bool:
        return all(d.ok for outputs in self.diffs.values() for d in outputs.values())

    def lines(self) -> list[str]:
        out = []
        for source, outputs in self.diffs.items():
            for name, d in outputs.items():
                rtol, atol = TOLERANCES[name]
                extra = f", top-K boundary swaps {d.boundary_swaps}" if d.boundary_swaps else ""
                extra += f", UNMATCHED {d.unmatched}" if d.unmatched else ""
                verdict = f"{'ok' if d.ok else 'FAIL'}, {d.worst:.1%} of tolerance{extra}"
                out.append(
                    f"  {source:8s} {name:8s} max abs {d.max_abs:.3e}  max rel {d.max_rel:.3e}  "
                    f"(rtol {rtol:g}, atol {atol:g}: {verdict}) over {self.cases[source]} windows"
                )
        return out


def compare_dense(ort: np.ndarray, ref: np.ndarray, rtol: float, atol: float) -> Diff:
    ort, ref = np.asarray(ort, np.float64), np.asarray(ref, np.float64)
    if ort.shape != ref.shape:
        raise VerificationError(f"shape mismatch: onnxruntime {ort.shape} vs torch {ref.shape}")
    if ort.size == 0:
        return Diff()
    err = np.abs(ort - ref)
    err[np.isnan(err)] = np.inf
    return Diff(
        max_abs=float(err.max()),
        max_rel=float((err / np.maximum(np.abs(ref), atol)).max()),
        worst=float((err / (atol + rtol * np.abs(ref))).max()),
    )


def compare_detections(
    ort_boxes: np.ndarray, ort_scores: np.ndarray, ref_boxes: np.ndarray, ref_scores: np.ndarray
) -> tuple[Diff, Diff]:
    """Match ORT detections to PyTorch ones as sets -> (boxes diff, scores diff)."""
    ort_boxes, ref_boxes = np.asarray(ort_boxes, np.float64), np.asarray(ref_boxes, np.float64)
    ort_scores, ref_scores = np.asarray(ort_scores, np.float64), np.asarray(ref_scores, np.float64)
    s_rtol, s_atol = TOLERANCES["scores"]
    b_rtol, b_atol = TOLERANCES["boxes"]
    box_diff, score_diff = Diff(), Diff()
    used = np.zeros(len(ref_scores), bool)
    boundary = ref_scores.min() if len(ref_scores) else 0.0
    for k in np.argsort(-ort_scores, kind="stable"):
        at_boundary = abs(ort_scores[k] - boundary) <= s_atol + s_rtol * abs(boundary)
        close = ~used & (np.abs(ref_scores - ort_scores[k]) <= s_atol + s_rtol * np.abs(ref_scores))
        matched = None
        if close.any():
            candidates = np.flatnonzero(close)
            j = candidates[np.argmin(np.linalg.norm(ref_boxes[candidates, :2] - ort_boxes[k, :2], axis=1))]
            delta = ort_boxes[k] - ref_boxes[j]
            delta[4] = (delta[4] + np.pi) % (2 * np.pi) - np.pi  # yaw near +-pi may wrap
            matched = compare_dense(ref_boxes[j] + delta, ref_boxes[j], b_rtol, b_atol)
        if matched is None or (not matched.ok and at_boundary):
            # no partner: fine only at the top-K boundary, where a tie may have kept another cell
            if at_boundary:
                box_diff.boundary_swaps += 1
            else:
                box_diff.unmatched += 1
            continue
        used[j] = True
        box_diff.update(matched)
        score_diff.update(compare_dense(ort_scores[k : k + 1], ref_scores[j : j + 1], s_rtol, s_atol))
    return box_diff, score_diff


def _detections(outputs: dict[str, np.ndarray | None], name: str) -> np.ndarray:
    """outputs["boxes"] / outputs["scores"], which every form has (only flow is None, for T = 1)."""
    value = outputs[name]
    if value is None:
        raise VerificationError(f"{name}: missing")
    return value


def compare_outputs(
    report: Report, source: str, ort: dict[str, np.ndarray | None], ref: dict[str, np.ndarray | None]
) -> None:
    """ort/ref: heatmap [Hf,Wf], boxes [K,5], scores [K], flow [2,Hf,Wf] or None (batch dimension dropped)."""
    report.cases[source] = report.cases.get(source, 0) + 1
    for name in ("heatmap", "flow"):
        ort_value, ref_value = ort.get(name), ref.get(name)
        if ref_value is not None or ort_value is not None:
            if ref_value is None or ort_value is None:
                raise VerificationError(f"{name}: present in only one of onnxruntime / torch")
            report.add(source, name, compare_dense(ort_value, ref_value, *TOLERANCES[name]))
    boxes, scores = compare_detections(
        _detections(ort, "boxes"), _detections(ort, "scores"), _detections(ref, "boxes"), _detections(ref, "scores")
    )
    report.add(source, "boxes", boxes)
    report.add(source, "scores", scores)


def window_from_history(
    frames: Sequence[np.ndarray] | np.ndarray, poses: np.ndarray | Sequence[np.ndarray], num_frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """A stream's history (oldest first, any length >= 1) -> its newest window under the warm-up rule of RaFD.step:
    the last T frames, padded at the old end by repeating the oldest of them with its pose when fewer than T are
    available. Returns (frames [T, ...] stacked as given, poses float64 [T, 3])."""
    frames = list(frames)[-num_frames:]
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)[-num_frames:]
    if not frames:
        raise ValueError("window_from_history needs at least one frame")
    if len(poses) != len(frames):
        raise ValueError(f"got {len(frames)} frames but {len(poses)} poses")
    pad = num_frames - len(frames)
    return np.stack([frames[0]] * pad + frames), np.concatenate([np.repeat(poses[:1], pad, axis=0), poses])


@torch.no_grad()
def torch_window(model: nn.Module, frames: np.ndarray, poses: np.ndarray) -> dict[str, np.ndarray | None]:
    """model.forward on one window: frames [T,S,S] in [0,1], world poses [T,3] -> outputs without the batch
    dimension, the flow the newest pair's [2,Hf,Wf]. The poses are taken relative to the newest in float64 first,
    as a stream's are."""
    local = relative_pose(np.asarray(poses, np.float64), np.asarray(poses, np.float64)[-1])
    out = model(
        torch.from_numpy(np.asarray(frames, np.float32))[None, :, None],
        torch.from_numpy(local.astype(np.float32))[None],
    )
    flow = out.get("flow")
    return {
        "heatmap": out["heatmap"][0, 0].numpy(),
        "boxes": out["boxes"][0].numpy(),
        "scores": out["scores"][0].numpy(),
        "flow": None if flow is None else flow[0, -1].numpy(),
    }


def verify_stream(
    runner: StreamRunner,
    model: nn.Module,
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    report: Report,
    source: str,
) -> None:
    """Stream one or more views (frames [N,S,S] / world poses [N,3] each, the same N) through the runner as one
    stream, all views in one run per frame; compare every view's every frame, the warm-up frames included, with
    model.forward on its own padded window."""
    T = runner.config.num_frames
    state = runner.new_state()
    for n in range(len(views[0][0])):
        frames = np.stack([np.asarray(f[n], np.float32) for f, _ in views])
        poses = np.stack([p[n] for _, p in views])
        result, state = runner.step(state, frames, poses)
        if result.frames_used != min(n + 1, T):
            raise VerificationError(f"frame {n}: frames_used {result.frames_used}, expected {min(n + 1, T)}")
        for v, (view_frames, view_poses) in enumerate(views):
            window = window_from_history(view_frames[: n + 1], view_poses[: n + 1], T)
            ort = {
                "heatmap": result.heatmap[v],
                "boxes": result.boxes[v],
                "scores": result.scores[v],
                "flow": None if result.flow is None else result.flow[v],
            }
            compare_outputs(report, source, ort, torch_window(model, *window))


def random_sequence(
    cfg: RaFDConfig, length: int, seed: int = 0, step_m: float = 1.5, step_rad: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Random frames [N,S,S] in [0,1] (sparse bright blobs on noise) and a random ego trajectory [N,3]."""
    rng = np.random.default_rng(seed)
    S = cfg.input_size
    frames = (rng.random((length, S, S)) * 0.3).astype(np.float32)
    for frame in frames:  # a few bright targets so heatmap peaks are not all ties
        for u, v in rng.integers(4, S - 4, size=(6, 2)):
            frame[v - 2 : v + 2, u - 3 : u + 3] = rng.uniform(0.6, 1.0)
    steps = rng.normal(0.0, 1.0, size=(length, 3)) * np.array([step_m, step_m, step_rad])
    steps[0] = rng.normal(0.0, 10.0, size=3)  # an arbitrary start pose
    return frames, np.cumsum(steps, axis=0)


def radiate_sequence(folder: str | os.PathLike[str], cfg: RaFDConfig, length: int) -> tuple[np.ndarray, np.ndarray]:
    """The first `length` Navtech_Cartesian frames of a RADIATE sequence as model inputs (rafd.preprocess), with
    poses from rafd.odometry.registration when it is available (zeros otherwise)."""
    import cv2

    from rafd.preprocess import model_crop, to_model_input

    paths = sorted(Path(folder, "Navtech_Cartesian").glob("*.png"))[:length]
    if not paths:
        raise FileNotFoundError(f"{folder}/Navtech_Cartesian holds no .png frames")
    images = []
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"cannot read {path}")
        images.append(model_crop(image, cfg.input_size))
    frames = to_model_input(np.stack(images))
    try:
        from rafd.odometry.registration import estimate_sequence_poses
    except ImportError:
        return frames, np.zeros((len(frames), 3))
    return frames, np.asarray(estimate_sequence_poses(np.stack(images), cfg.resolution), np.float64)


def verify_export(
    onnx_path: str | os.PathLike[str],
    model: nn.Module,
    cfg: RaFDConfig,
    log: Callable[[str], None] = print,
    length: int | None = None,
) -> Report:
    """Random inputs and, when RAFD_RADIATE_SAMPLE names a RADIATE sequence, real frames. Raises VerificationError
    beyond tolerance (after logging the differences)."""
    runner = OnnxRunner(onnx_path)
    length = length or cfg.num_frames + 3  # warm-up frames + a few full windows
    sources = {"random": random_sequence(cfg, length)}
    sample = os.environ.get("RAFD_RADIATE_SAMPLE")
    if sample:
        if Path(sample, "Navtech_Cartesian").is_dir():
            sources["radiate"] = radiate_sequence(sample, cfg, length)
        else:
            log(f"warning: RAFD_RADIATE_SAMPLE={sample} holds no Navtech_Cartesian/ folder; real frames skipped")
    report = Report()
    model = model.eval()
    for source, sequence in sources.items():
        verify_stream(runner, model, [sequence], report, source)
    if runner.batch == DYNAMIC:  # the views of one stream (a whole scan's tiles) step as one batch
        views = [random_sequence(cfg, cfg.num_frames + 1, seed=seed) for seed in (1, 2)]
        verify_stream(runner, model, views, report, "batched")
    log("parity onnxruntime vs PyTorch (streamed through OnnxRunner vs padded windows):")
    for line in report.lines():
        log(line)
    if not report.ok:
        raise VerificationError(
            f"{onnx_path}: onnxruntime outputs differ from PyTorch beyond tolerance (see the differences above)"
        )
    return report
