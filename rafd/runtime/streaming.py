"""Streaming an exported step graph (numpy only): a stream's state is the graph's cache plus the last frame's poses.

A stream may have several views (the tiles of a whole scan, rafd.tiles): they step together, as one batch of the
graph, each with its own cache and world pose. The runner carries the graph's new_cache.NAME outputs to the next
step's cache.NAME inputs without knowing what they hold (rafd.runtime.contract); what it does itself:

- poses: world poses (float64, possibly large UTM metres) become the graph's `pose`, each view's pose in its
  previous pose's ego frame, in float64 before the cast to float32 (rafd.geometry.relative_pose); the state keeps
  the world poses for the next step;
- a new stream's cache is zeros of the graph's cache shapes (the model warms itself up from there);
- `step` is pure: the old state stays valid and can be stepped again (the service commits the new state only when
  the whole request succeeded). States are immutable and their arrays read-only.

The runner is backend-independent: a rafd.runtime.backend.Backend (onnxruntime fp32, OpenVINO bf16/fp32/int8, or
PyTorch for evaluation) only runs the graph; states hold float32 numpy arrays whatever the backend computes in.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Protocol

import numpy as np

from rafd.config import RaFDConfig
from rafd.geometry import relative_pose
from rafd.runtime.backend import DYNAMIC, Backend, shapes_at
from rafd.runtime.contract import cache_names, carried, check_step_graph


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


@dataclass(frozen=True)
class StreamState:
    """One stream's state after its last frame: the graph's cache and the views' world poses ([] and None: new)."""

    cache: Mapping[str, np.ndarray] = field(default_factory=lambda: MappingProxyType({}))  # cache.NAME -> [V, ...]
    poses: np.ndarray | None = None  # [V, 3] float64 world poses of the last frame's views
    frames_used: int = 0  # real frames in the last window

    @property
    def views(self) -> int:
        return 0 if self.poses is None else len(self.poses)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.cache.values()) + (0 if self.poses is None else self.poses.nbytes)


@dataclass(frozen=True)
class StepResult:
    """One step's outputs, per view (the leading axis V), or one view's (`view(v)`: the same without that axis)."""

    heatmap: np.ndarray  # [V, Hf, Wf] logits
    boxes: np.ndarray  # [V, K, 5] (x, y, width, length, yaw), metres, each view's newest ego frame
    scores: np.ndarray  # [V, K] in [0, 1]
    flow: np.ndarray | None  # [V, 2, Hf, Wf] metres, the newest pair's flow (None for T = 1)
    frames_used: int  # real frames in the window

    def view(self, v: int) -> StepResult:
        return StepResult(
            self.heatmap[v],
            self.boxes[v],
            self.scores[v],
            None if self.flow is None else self.flow[v],
            self.frames_used,
        )


class Runner(Protocol):
    """What a server needs of a streaming runner (StreamRunner, and the tests' stand-ins)."""

    config: RaFDConfig
    metadata: dict[str, str]

    @property
    def runtime(self) -> str: ...

    @property
    def precision(self) -> str: ...

    def new_state(self) -> StreamState: ...

    def step(self, state: StreamState, frames: np.ndarray, poses: np.ndarray) -> tuple[StepResult, StreamState]:
        """(state, float32 [V, S, S] frames in [0, 1], world poses [V, 3]) -> (the result, the new state)."""
        ...

    def describe(self) -> dict[str, object]: ...

    def state_bytes(self, views: int) -> int: ...


class StreamRunner:
    """Streams frames through one backend's step graph; thread-safe, stateless.

    Concurrency: a run that starts while no other run is in flight uses `backend` (all its threads: the lowest
    latency for one stream); a run that starts while others are in flight uses `crowd` (the same graph compiled
    with fewer threads per run, e.g. 1 of 2 cores each), so several streams run side by side instead of
    contending for one thread pool. At most max(backend, crowd).concurrent_runs runs execute at once; more
    callers wait.
    """

    def __init__(self, backend: Backend, crowd: Backend | None = None) -> None:
        self.backend, self.crowd = backend, crowd
        self.path = path = getattr(backend, "path", "the model")
        self.selection: dict[str, float] = {}  # create_runner("auto"): median ms per run of each candidate
        # create_runner: the precisions this CPU runs, the model's gate records, and why it serves what it serves
        self.precision_choice: dict[str, object] | None = None
        self.metadata: dict[str, str] = dict(backend.metadata)
        if "config" not in self.metadata:
            raise ValueError(
                f"{path} is not a RaFD export: its metadata has no 'config' (keys: {sorted(self.metadata)})"
            )
        self.config = RaFDConfig.from_json(self.metadata["config"])
        shapes = backend.input_shapes
        check_step_graph(str(path), shapes, tuple(backend.output_names), self.config.num_frames)
        size = self.config.input_size
        if tuple(shapes["frame"][-2:]) != (size, size):
            raise ValueError(f"{path}: input frame shape {shapes['frame']} does not match input_size {size}")
        self.cache_names = cache_names(tuple(shapes))
        self._cache_shapes = {name: tuple(shapes[name][1:]) for name in self.cache_names}
        self.batch = shapes["frame"][0]  # DYNAMIC: any number of views in one run
        if crowd is not None and (crowd.runtime, crowd.precision, crowd.input_shapes) != (
            backend.runtime,
            backend.precision,
            backend.input_shapes,
        ):
            raise ValueError("the crowd backend must run the same graph on the same runtime and precision")
        self.concurrent_runs = max(1, backend.concurrent_runs, crowd.concurrent_runs if crowd is not None else 1)
        self._slots = threading.BoundedSemaphore(self.concurrent_runs)
        self._in_flight = 0
        self._in_flight_lock = threading.Lock()

    @property
    def runtime(self) -> str:
        return self.backend.runtime

    @property
    def precision(self) -> str:
        return self.backend.precision

    @property
    def threads(self) -> int:
        return self.backend.threads

    def describe(self) -> dict[str, object]:
        """How the graph runs: runtime, precision (with its float32 islands, if any), threads of a lone run,
        concurrent runs and their threads."""
        crowd = self.crowd or self.backend
        described: dict[str, object] = {
            "runtime": self.runtime,
            "precision": self.precision,
            "threads": self.threads,
            "concurrent_runs": self.concurrent_runs,
            "threads_per_concurrent_run": crowd.threads,
            "selection_ms_per_run": dict(self.selection),
            "float32_islands": list(getattr(self.backend, "islands", ())),
        }
        if self.precision_choice is not None:  # a runner create_runner chose (the service's)
            described["precision_choice"] = self.precision_choice
        return described

    # ------------------------------------------------------------------ API
    def new_state(self) -> StreamState:
        return StreamState()

    def state_bytes(self, views: int) -> int:
        """What a stream of `views` views holds once it has stepped (StreamState.nbytes)."""
        per_view = sum(4 * int(np.prod(shape)) for shape in self._cache_shapes.values()) + 3 * 8
        return views * per_view

    def warm(self, views: Sequence[int]) -> None:
        """Run each backend this runner may use (a lone run's and the crowd's) once per batch of `views` rows, on
        zeros: their first-run costs (allocations, kernel choices, OpenVINO's compilation of a static shape) are paid
        here, not by the first request, or the first concurrent ones, of each size."""
        batches = sorted({view if self.batch == DYNAMIC else 1 for view in views})
        for backend in (self.backend,) if self.crowd is None else (self.backend, self.crowd):
            for batch in batches:
                backend.run(
                    {
                        name: np.zeros(shape, np.float32)
                        for name, shape in shapes_at(backend.input_shapes, batch).items()
                    }
                )

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """One raw graph run -> {output name: array}; a graph of static batch 1 runs a batch view by view."""
        if self.batch != DYNAMIC and len(feeds["frame"]) != self.batch:
            runs = [
                self.run({name: value[v : v + 1] for name, value in feeds.items()}) for v in range(len(feeds["frame"]))
            ]
            return {name: np.concatenate([out[name] for out in runs]) for name in runs[0]}
        with self._slots:
            with self._in_flight_lock:
                alone = self._in_flight == 0
                self._in_flight += 1
            try:
                return (self.backend if alone or self.crowd is None else self.crowd).run(feeds)
            finally:
                with self._in_flight_lock:
                    self._in_flight -= 1

    def step(self, state: StreamState, frames: np.ndarray, poses: np.ndarray) -> tuple[StepResult, StreamState]:
        """Add one frame of each view (float32 [V, S, S] in [0, 1]) with its world pose ([V, 3]) -> (the result for
        each view's window, the new state). A state of other views than these is refused (ValueError)."""
        frames, poses = self._checked_frames(frames), self._checked_poses(poses, len(frames))
        views = len(frames)
        if state.poses is None:  # a new stream: the graph starts from zeros
            cache = {name: np.zeros((views, *shape), np.float32) for name, shape in self._cache_shapes.items()}
            motion = np.zeros((views, 3), np.float32)
        elif state.views != views:
            raise ValueError(f"the stream's state holds {state.views} views, this frame {views}")
        else:
            cache = dict(state.cache)
            motion = relative_pose(poses, state.poses).astype(np.float32)  # each view in its last pose's frame
        out = self.run({"frame": frames[:, None], "pose": motion, **cache})
        new_state = StreamState(
            cache=MappingProxyType({name: _frozen(out[carried(name)]) for name in self.cache_names}),
            poses=_frozen(poses),
            frames_used=int(np.max(out["frames_used"])),
        )
        flow = out.get("flow")
        result = StepResult(
            heatmap=out["heatmap"][:, 0],
            boxes=out["boxes"],
            scores=out["scores"],
            flow=flow,
            frames_used=new_state.frames_used,
        )
        return result, new_state

    def _checked_frames(self, frames: np.ndarray) -> np.ndarray:
        size = self.config.input_size
        if (
            not isinstance(frames, np.ndarray)
            or frames.dtype != np.float32
            or frames.ndim != 3
            or frames.shape[1:] != (size, size)
            or not len(frames)
        ):
            raise ValueError(
                f"frames must be float32 [V, {size}, {size}], got "
                f"{getattr(frames, 'dtype', type(frames).__name__)} {getattr(frames, 'shape', '')}"
            )
        if not (frames.min() >= 0.0 and frames.max() <= 1.0):  # also false for NaN
            raise ValueError("frame values must lie in [0, 1]")
        return np.ascontiguousarray(frames)

    @staticmethod
    def _checked_poses(poses: np.ndarray, views: int) -> np.ndarray:
        poses = np.array(poses, dtype=np.float64)  # a copy: the state keeps it
        if poses.shape != (views, 3) or not np.all(np.isfinite(poses)):
            raise ValueError(f"poses must be [{views}, 3] finite numbers, got {poses!r}")
        return poses
