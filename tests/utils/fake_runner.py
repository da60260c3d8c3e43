"""A deterministic numpy stand-in for an exported step graph (FakeBackend), run by the real rafd.runtime.StreamRunner:
the fake follows the runtime contract because it is run through it.

The fake graph's cache holds the last T-1 frames' cells and poses; its outputs are simple functions of the stream's
padded window (the warm-up rule: a window of fewer than T frames repeats its oldest), so tests can recompute them:
- cells: a frame mean-pooled to the feature grid [Hf, Wf]; heatmap = the newest frame's cells;
- boxes: the K brightest cells (ties by flat index), centred on the cell centre, width 1.5 + value, length 4,
  yaw = the newest pose's yaw - the oldest's; scores = the cell values;
- flow of the newest pair (a, b): x = 255 * (cells_b - cells_a), y = b's x - a's x in b's ego frame.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np

from rafd.config import RaFDConfig
from rafd.geometry import feature_cell_centres, relative_pose, wrap_angle
from rafd.runtime import StreamRunner
from rafd.runtime.backend import DYNAMIC


class FakeBackend:
    """A rafd.runtime.backend.Backend computing the fake graph in numpy; counts its runs."""

    runtime = "fake"
    precision = "fp32"
    threads = 1
    concurrent_runs = 4

    def __init__(self, config: RaFDConfig, delay_s: float = 0.0, gate: threading.Event | None = None) -> None:
        self.config = config
        self.metadata = {
            "config": config.to_json(),
            "input_size": str(config.input_size),
            "resolution": str(config.resolution),
            "num_frames": str(config.num_frames),
            "class_names": json.dumps(list(config.class_names)),
            "checkpoint_sha256": "0" * 64,
            "version": "fake-1",
        }
        S, F, T = config.input_size, config.feature_size, config.num_frames
        self.input_shapes: dict[str, tuple[int, ...]] = {"frame": (DYNAMIC, 1, S, S), "pose": (DYNAMIC, 3)}
        if T > 1:
            self.input_shapes |= {
                "cache.cells": (DYNAMIC, T - 1, F, F),
                "cache.poses": (DYNAMIC, T - 1, 3),
                "cache.frames": (DYNAMIC,),
            }
        caches = tuple("new_" + name for name in self.input_shapes if name.startswith("cache."))
        flow = ("flow",) if T > 1 else ()
        self.output_names = ("heatmap", "scores", "boxes", *flow, "frames_used", *caches)
        self.delay_s = delay_s
        self.gate = gate  # when set, run() waits for it (to hold the app in "loading")
        self.calls = 0
        self.at_gate = 0  # runs blocked at the gate right now
        self.in_flight = 0
        self.max_in_flight = 0  # most runs seen at once (different streams run concurrently)
        self._lock = threading.Lock()

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self.gate is not None:
            with self._lock:
                self.at_gate += 1
            try:
                self.gate.wait(timeout=10.0)
            finally:
                with self._lock:
                    self.at_gate -= 1
        with self._lock:
            self.calls += 1
            self.in_flight += 1
            self.max_in_flight = max(self.max_in_flight, self.in_flight)
        try:
            if self.delay_s:
                time.sleep(self.delay_s)
            rows = [self._row({name: value[b] for name, value in feeds.items()}) for b in range(len(feeds["frame"]))]
            return {name: np.stack([row[name] for row in rows]) for name in self.output_names}
        finally:
            with self._lock:
                self.in_flight -= 1

    def _row(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        cfg = self.config
        T, K = cfg.num_frames, cfg.head.num_queries
        newest = self._cells(feeds["frame"][0])  # [Hf, Wf]
        pose = feeds["pose"].astype(np.float64)  # this frame in the previous one's ego frame
        out: dict[str, np.ndarray] = {}
        if T == 1:
            cells, poses = [newest], np.zeros((1, 3))
            out["frames_used"] = np.float32(1.0)
        else:
            seen = float(feeds["cache.frames"])
            if seen > 0:
                past_cells = list(feeds["cache.cells"])
                past_poses = relative_pose(feeds["cache.poses"].astype(np.float64), pose)  # into this frame
            else:
                past_cells, past_poses = [newest] * (T - 1), np.zeros((T - 1, 3))
            cells, poses = past_cells + [newest], np.concatenate([past_poses, np.zeros((1, 3))])
            out["flow"] = np.stack([255.0 * (cells[-1] - cells[-2]), np.full_like(newest, -poses[-2][0])])
            out["frames_used"] = np.float32(min(seen + 1, T))
            out["new_cache.cells"] = np.stack(cells[1:])
            out["new_cache.poses"] = poses[1:]
            out["new_cache.frames"] = out["frames_used"]
        order = np.argsort(-newest.reshape(-1), kind="stable")[:K]  # [K] flat cell indices
        centres = feature_cell_centres(cfg.feature_size, cfg.input_size, cfg.resolution).reshape(-1, 2)
        boxes = np.zeros((K, 5))
        boxes[:, :2] = centres[order]
        boxes[:, 2] = 1.5 + newest.reshape(-1)[order]
        boxes[:, 3] = 4.0
        boxes[:, 4] = wrap_angle(-poses[0][2])  # the newest pose's yaw (0 here) - the oldest's
        out |= {"heatmap": newest[None], "scores": newest.reshape(-1)[order], "boxes": boxes}
        return {name: np.asarray(value, np.float32) for name, value in out.items()}

    def _cells(self, frame: np.ndarray) -> np.ndarray:
        """[S, S] -> [Hf, Wf] mean over each cell's stride x stride pixels."""
        f = self.config.feature_size
        s = self.config.input_size // f
        return frame.reshape(f, s, f, s).mean(axis=(1, 3)).astype(np.float64)


# Runs of the service's warm-up on a FakeRunner of the default config (service.loading.warm_up): a step on a blank
# frame, then its backend at one view and at a whole scan's tiles.
WARM_UP_RUNS = 3


class FakeRunner(StreamRunner):
    """StreamRunner over a FakeBackend; its counters read through."""

    backend: FakeBackend

    def __init__(
        self, config: RaFDConfig | None = None, delay_s: float = 0.0, gate: threading.Event | None = None
    ) -> None:
        # 128x128 input, 4 frames, 32x32 cells, K = 32 by default
        super().__init__(FakeBackend(config or RaFDConfig.tiny(), delay_s, gate))

    @property
    def calls(self) -> int:
        return self.backend.calls

    @property
    def max_in_flight(self) -> int:
        return self.backend.max_in_flight

    @property
    def at_gate(self) -> int:
        return self.backend.at_gate
