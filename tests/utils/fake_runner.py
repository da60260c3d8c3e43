"""A deterministic numpy stand-in for rafd.runtime.OnnxRunner, following the runtime contract exactly.

Its outputs are simple functions of the stream's own window, so tests can recompute them:
- window: the last T frames with poses, padded at the old end by repeating the oldest (warm-up rule);
- cells: the NEWEST frame mean-pooled to the feature grid [Hf, Wf]; heatmap = cells;
- boxes: the K brightest cells (ties by flat index), centred on the cell centre, width 1.5 + value,
  length 4, yaw = newest pose yaw - oldest pose yaw; scores = the cell values;
- flow per consecutive pair (a, b): x = 255 * (cells_b - cells_a), y = pose_b.x - pose_a.x.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass

import numpy as np

from rafd.config import RaFDConfig
from rafd.geometry import feature_cell_centres, wrap_angle


@dataclass(frozen=True)
class FakeState:
    frames: tuple[np.ndarray, ...] = ()  # each [S, S] float32, oldest first
    poses: tuple[np.ndarray, ...] = ()  # each [3]

    @property
    def frames_used(self) -> int:
        return len(self.frames)

    @property
    def nbytes(self) -> int:
        return sum(f.nbytes for f in self.frames) + sum(p.nbytes for p in self.poses)


@dataclass(frozen=True)
class FakeStepResult:
    heatmap: np.ndarray  # [Hf, Wf]
    boxes: np.ndarray  # [K, 5]
    scores: np.ndarray  # [K]
    flow: np.ndarray | None  # [T-1, 2, Hf, Wf]
    frames_used: int


class FakeRunner:
    runtime = "fake"
    precision = "fp32"

    def __init__(
        self, config: RaFDConfig | None = None, delay_s: float = 0.0, gate: threading.Event | None = None
    ) -> None:
        self.config = config or RaFDConfig.tiny()  # 128x128 input, 4 frames, 32x32 cells, K = 32
        self.metadata = {
            "config": self.config.to_json(),
            "input_size": str(self.config.input_size),
            "resolution": str(self.config.resolution),
            "num_frames": str(self.config.num_frames),
            "class_names": json.dumps(list(self.config.class_names)),
            "checkpoint_sha256": "0" * 64,
            "version": "fake-1",
        }
        self.delay_s = delay_s
        self.gate = gate  # when set, step() waits for it (to hold the app in "loading")
        self.calls = 0
        self.at_gate = 0  # steps blocked at the gate right now
        self.in_flight = 0
        self.max_in_flight = 0  # most steps seen running at once (different streams run concurrently)
        self._calls_lock = threading.Lock()

    def new_state(self) -> FakeState:
        return FakeState()

    def describe(self) -> dict[str, object]:
        """As rafd.runtime.StreamRunner.describe: how the graph runs."""
        return {
            "runtime": self.runtime,
            "precision": self.precision,
            "threads": 1,
            "concurrent_runs": 1,
            "threads_per_concurrent_run": 1,
            "selection_ms_per_run": {},
            "float32_islands": [],
        }

    def step(self, state: FakeState, frame: np.ndarray, pose: np.ndarray) -> tuple[FakeStepResult, FakeState]:
        size = self.config.input_size
        if frame.dtype != np.float32 or frame.shape != (size, size):
            raise ValueError(f"frame must be float32 [{size}, {size}], got {frame.dtype} {frame.shape}")
        if not (np.all(frame >= 0.0) and np.all(frame <= 1.0)):
            raise ValueError("frame values must lie in [0, 1]")
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be 3 finite numbers, got {pose!r}")
        if self.gate is not None:
            with self._calls_lock:
                self.at_gate += 1
            try:
                self.gate.wait(timeout=10.0)
            finally:
                with self._calls_lock:
                    self.at_gate -= 1
        with self._calls_lock:
            self.calls += 1
            self.in_flight += 1
            self.max_in_flight = max(self.max_in_flight, self.in_flight)
        try:
            if self.delay_s:
                time.sleep(self.delay_s)
            return self._step(state, frame, pose)
        finally:
            with self._calls_lock:
                self.in_flight -= 1

    def _step(self, state: FakeState, frame: np.ndarray, pose: np.ndarray) -> tuple[FakeStepResult, FakeState]:
        size = self.config.input_size

        T = self.config.num_frames
        new_state = FakeState(frames=(state.frames + (frame.copy(),))[-T:], poses=(state.poses + (pose.copy(),))[-T:])
        pad = T - new_state.frames_used
        frames = (new_state.frames[0],) * pad + new_state.frames
        poses = (new_state.poses[0],) * pad + new_state.poses
        cells = [self._cells(f) for f in frames]  # T x [Hf, Wf]

        newest = cells[-1]
        k = self.config.head.num_queries
        order = np.argsort(-newest.reshape(-1), kind="stable")[:k]  # [K] flat cell indices
        centres = feature_cell_centres(self.config.feature_size, size, self.config.resolution).reshape(-1, 2)
        boxes = np.zeros((k, 5))
        boxes[:, :2] = centres[order]
        boxes[:, 2] = 1.5 + newest.reshape(-1)[order]
        boxes[:, 3] = 4.0
        boxes[:, 4] = wrap_angle(poses[-1][2] - poses[0][2])
        flow = None
        if T > 1:
            flow = np.stack(
                [
                    np.stack([255.0 * (cells[t] - cells[t - 1]), np.full_like(newest, poses[t][0] - poses[t - 1][0])])
                    for t in range(1, T)
                ]
            ).astype(np.float32)  # [T-1, 2, Hf, Wf]
        result = FakeStepResult(
            heatmap=newest.astype(np.float32),
            boxes=boxes.astype(np.float32),
            scores=newest.reshape(-1)[order].astype(np.float32),
            flow=flow,
            frames_used=new_state.frames_used,
        )
        return result, new_state

    def _cells(self, frame: np.ndarray) -> np.ndarray:
        """[S, S] -> [Hf, Wf] mean over each cell's stride x stride pixels."""
        f = self.config.feature_size
        s = self.config.input_size // f
        return frame.reshape(f, s, f, s).mean(axis=(1, 3)).astype(np.float64)
