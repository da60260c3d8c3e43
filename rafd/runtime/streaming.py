"""The streaming logic every backend shares (numpy only): stream states, warm-up, the first-frame procedure.

Warm-up rule (the same in PyTorch and ONNX): a window with fewer than T real frames is padded at the OLD end by
repeating the oldest real frame with its pose, e.g. for T = 4 the windows of a stream f1, f2, f3, f4, f5, ... are
[f1 f1 f1 f1], [f1 f1 f1 f2], [f1 f1 f2 f3], [f1 f2 f3 f4], [f2 f3 f4 f5], ...  `window_from_history` builds that
window from a stream's history (the PyTorch side of the comparison uses it).

Step graph (exported by `rafd-export --form step`, the service's form): per frame it encodes only the new frame,
computes only the newest pair's flow and runs the propagation chain + head:
    inputs  frame [1,1,S,S], poses [1,T,3] (window, oldest first, last = this frame),
            past_features [1,T-1,C,Hf,Wf], past_flows [1,T-2,2,Hf,Wf] (T = 4 only),
            past_flow_features [1,C/2,Hm,Wm] (the previous frame's phi output)
    outputs heatmap [1,1,Hf,Wf], scores [1,K], boxes [1,K,5], flow [1,T-1,2,Hf,Wf], features [1,C,Hf,Wf],
            flow_features [1,C/2,Hm,Wm]
For T = 1 the step graph is the single-frame model (inputs frame, poses [1,1,3]; no caches, no flow). Step graphs
exported before the flow-feature cache (no past_flow_features input) are run the same way without it.

Since each padded window is the previous one shifted by one frame, the state simply holds the previous window's
caches, already padded: the last T-1 features, the last T-2 pair flows, the last T-1 world poses and the newest
frame's flow features.

First frame of a stream (no caches yet), for T > 1:
  1. run with zero caches: only its `features` output F1 (and `flow_features` E1) is used;
  2. run with past_features = [F1] * (T-1), past_flow_features = E1 (and zero past_flows): its newest `flow`
     output is the self-pair flow S1 = pair_flow(F1, F1, identity). For T = 2 there are no past flows, so this
     run is already the result for the window [f1 f1];
  3. (T = 4 only) run with past_features = [F1] * 3 and past_flows = [S1] * 2: the result for [f1 f1 f1 f1].
  (The third run is needed because the detection of run 2 saw zero past flows; it happens once per stream.)

Poses: world poses may be large (UTM metres), so the window's poses are re-expressed in float64 in the newest
frame's ego frame (newest pose = (0, 0, 0)) before the cast to float32. The model only uses relative poses, which
do not change under that rigid change of world frame.

Window form (`rafd-export --form window`, model.forward on the whole window): the state keeps the last T-1 frames
instead and every step runs the full padded window (the same results, without the caching).

`step` is pure: the old state stays valid and can be stepped again (the service commits the new state only when
the whole request succeeded). States are immutable and their cached arrays are read-only.

The runner is backend-independent: a rafd.runtime.backend.Backend (onnxruntime fp32, OpenVINO bf16/fp32) only runs
the graph; states hold float32 numpy arrays whatever the backend computes in.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from rafd.config import RaFDConfig
from rafd.geometry import relative_pose
from rafd.runtime.backend import DYNAMIC, Backend
from rafd.runtime.contract import FORMS, graph_inputs, graph_outputs


def window_from_history(
    frames: Sequence[np.ndarray] | np.ndarray, poses: np.ndarray | Sequence[np.ndarray], num_frames: int
) -> tuple[np.ndarray, np.ndarray]:
    """A stream's history (oldest first, any length >= 1) -> its newest window under the warm-up rule.

    Returns (frames [T, ...] stacked as given, poses float64 [T, 3]): the last T frames, padded at the old end by
    repeating the oldest of them with its pose when fewer than T are available.
    """
    frames = list(frames)[-num_frames:]
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)[-num_frames:]
    if not frames:
        raise ValueError("window_from_history needs at least one frame")
    if len(poses) != len(frames):
        raise ValueError(f"got {len(frames)} frames but {len(poses)} poses")
    pad = num_frames - len(frames)
    return np.stack([frames[0]] * pad + frames), np.concatenate([np.repeat(poses[:1], pad, axis=0), poses])


def poses_in_newest_frame(poses: np.ndarray) -> np.ndarray:
    """World poses [T, 3] (float64) -> float32 [T, 3] expressed in the newest pose's ego frame.

    Pose i becomes geometry.relative_pose(pose_i, newest); relative poses between any two are unchanged, and the
    differences are taken in float64 before the cast, so large world coordinates lose no precision.
    """
    poses = np.asarray(poses, dtype=np.float64)
    return relative_pose(poses, poses[-1]).astype(np.float32)


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


@dataclass(frozen=True)
class StreamState:
    """One stream's caches: the previous window minus its oldest frame, padded by the warm-up rule, oldest first."""

    frames_used: int = 0  # real frames in the newest window: min(frames seen, T)
    poses: tuple[np.ndarray, ...] = ()  # T-1 world poses, float64 [3]
    features: tuple[np.ndarray, ...] = ()  # step form: T-1 per-frame features [C, Hf, Wf]
    flows: tuple[np.ndarray, ...] = ()  # step form: T-2 pair flows [2, Hf, Wf]
    frames: tuple[np.ndarray, ...] = ()  # window form: T-1 frames [S, S]
    flow_features: tuple[np.ndarray, ...] = ()  # step form with the flow cache: the newest frame's [C/2, Hm, Wm]

    @property
    def nbytes(self) -> int:
        """Bytes held (padding repeats one array, counted once)."""
        unique = {id(a): a for a in self.poses + self.features + self.flows + self.frames + self.flow_features}
        return sum(a.nbytes for a in unique.values())


@dataclass(frozen=True)
class StepResult:
    heatmap: np.ndarray  # [Hf, Wf] logits
    boxes: np.ndarray  # [K, 5] (x, y, width, length, yaw), metres, newest ego frame
    scores: np.ndarray  # [K] in [0, 1]
    flow: np.ndarray | None  # [T-1, 2, Hf, Wf] metres, the window's pair flows (None for T = 1)
    frames_used: int


class Runner(Protocol):
    """What a server needs of a streaming runner: StreamRunner implements it (and the tests' stand-ins do)."""

    config: RaFDConfig
    metadata: dict[str, str]

    @property
    def runtime(self) -> str: ...

    @property
    def precision(self) -> str: ...

    def new_state(self) -> Any: ...

    def step(self, state: Any, frame: np.ndarray, pose: np.ndarray) -> tuple[Any, Any]:
        """(state, float32 [S, S] frame, world pose [3]) -> (a StepResult-like answer, the new state)."""
        ...

    def describe(self) -> dict[str, object]: ...


class StreamRunner:
    """Streams frames through one backend's exported RaFD graph (step or window form); thread-safe, stateless.

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
        self.input_names = tuple(backend.input_shapes)
        self.output_names = tuple(backend.output_names)
        self.form = self.metadata.get("form") or ("window" if "frames" in self.input_names else "step")
        T = self.config.num_frames
        self.flow_cache = "past_flow_features" in self.input_names  # False: a step graph from before the cache
        expected = graph_inputs(self.form, T, self.flow_cache)
        needed_outputs = graph_outputs(self.form, T, self.flow_cache)
        if (
            self.form not in FORMS
            or set(self.input_names) != set(expected)
            or not set(needed_outputs) <= set(self.output_names)
        ):
            raise ValueError(
                f"{path}: not a RaFD {self.form!r} graph for T = {T}: inputs {self.input_names}, "
                f"outputs {self.output_names} (expected inputs {expected}, outputs {needed_outputs})"
            )
        shapes = backend.input_shapes
        size = self.config.input_size
        if self.form == "step" and T > 1:
            _, _, channels, height, width = shapes["past_features"]
            self._zero_features = _frozen(np.zeros((channels, height, width), np.float32))
            self._zero_flow = _frozen(np.zeros((2, height, width), np.float32))
            if self.flow_cache:
                self._zero_flow_features = _frozen(np.zeros(shapes["past_flow_features"][1:], np.float32))
        frame_shape = shapes["frames" if self.form == "window" else "frame"]
        if tuple(frame_shape[-2:]) != (size, size):
            raise ValueError(f"{path}: input frame shape {frame_shape} does not match input_size {size}")
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
        """How the graph runs: runtime, precision (with bf16's float32 islands, if any), threads of a lone run,
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

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """One raw graph run -> {output name: array}."""
        with self._slots:
            with self._in_flight_lock:
                alone = self._in_flight == 0
                self._in_flight += 1
            try:
                return (self.backend if alone or self.crowd is None else self.crowd).run(feeds)
            finally:
                with self._in_flight_lock:
                    self._in_flight -= 1

    @property
    def batchable(self) -> bool:
        """Whether the graph takes a batch of frames of different streams in one run (a dynamic first axis, from
        `rafd-export --batch dynamic`); step_many then runs streams' steady-state steps together."""
        return self.form == "step" and self.backend.input_shapes["frame"][0] == DYNAMIC

    def step_many(
        self, items: Sequence[tuple[StreamState, np.ndarray, np.ndarray]]
    ) -> list[tuple[StepResult, StreamState]]:
        """Several streams' next frames -> each one's (result, new state), in order: step() for each, but the
        streams past their first frame share one graph run when the graph is batchable (their caches stacked in,
        split out). A stream's first frame (its warm-up runs) and a graph without a batch axis run one by one."""
        out: list[tuple[StepResult, StreamState] | None] = [None] * len(items)
        together = []
        for index, (state, frame, pose) in enumerate(items):
            if self.batchable and len(items) > 1 and state.frames_used > 0:
                together.append((index, state, self._checked_frame(frame), self._checked_pose(pose)))
            else:
                out[index] = self.step(state, frame, pose)
        if together:
            feeds = [self._step_feeds(state, frame, pose) for _, state, frame, pose in together]
            stacked = {name: np.concatenate([f[name] for f in feeds]) for name in feeds[0]}
            batch = self.run(stacked)
            for row, (index, state, _, pose) in enumerate(together):
                own = {name: value[row : row + 1] for name, value in batch.items()}
                out[index] = self._after_step(state, pose, own)
        return [result for result in out if result is not None]

    def _checked_frame(self, frame: np.ndarray) -> np.ndarray:
        size = self.config.input_size
        if not isinstance(frame, np.ndarray) or frame.dtype != np.float32 or frame.shape != (size, size):
            raise ValueError(
                f"frame must be float32 [{size}, {size}], got "
                f"{getattr(frame, 'dtype', type(frame).__name__)} {getattr(frame, 'shape', '')}"
            )
        if not (frame.min() >= 0.0 and frame.max() <= 1.0):  # also false for NaN
            raise ValueError("frame values must lie in [0, 1]")
        return frame

    @staticmethod
    def _checked_pose(pose: np.ndarray) -> np.ndarray:
        pose = np.array(pose, dtype=np.float64)  # a copy: the state keeps it
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be 3 finite numbers, got {pose!r}")
        return _frozen(pose)

    def step(self, state: StreamState, frame: np.ndarray, pose: np.ndarray) -> tuple[StepResult, StreamState]:
        """Add one frame (float32 [S, S] in [0, 1]) with its world pose [3] -> (result for its window, new state)."""
        frame, pose = self._checked_frame(frame), self._checked_pose(pose)
        if self.form == "window":
            return self._step_window(state, frame, pose)
        if self.config.num_frames == 1:
            out = self.run(self._step_feeds(state, frame, pose))
            return self._result(out, 1), StreamState(frames_used=1)
        if state.frames_used == 0:
            return self._first_step(frame, pose)
        return self._after_step(state, pose, self.run(self._step_feeds(state, frame, pose)))

    # ------------------------------------------------------------------ step form
    def _step_feeds(self, state: StreamState, frame: np.ndarray, pose: np.ndarray) -> dict[str, np.ndarray]:
        """One steady-state step's graph inputs (batch of one)."""
        if self.config.num_frames == 1:
            return {"frame": frame[None, None], "poses": np.zeros((1, 1, 3), np.float32)}
        return self._feeds(frame, state.poses + (pose,), state.features, state.flows, state.flow_features)

    def _after_step(
        self, state: StreamState, pose: np.ndarray, out: dict[str, np.ndarray]
    ) -> tuple[StepResult, StreamState]:
        """A steady-state step's outputs (batch of one) -> (its result, the stream's new state)."""
        if self.config.num_frames == 1:
            return self._result(out, 1), StreamState(frames_used=1)
        poses = state.poses + (pose,)
        flows = state.flows
        if flows:  # T = 4: keep the newest T-2 pair flows (a copy: result.flow belongs to the caller)
            flows = flows[1:] + (_frozen(out["flow"][0, -1].copy()),)
        new_state = StreamState(
            frames_used=min(state.frames_used + 1, self.config.num_frames),
            poses=poses[1:],
            features=state.features[1:] + (_frozen(out["features"][0]),),
            flows=flows,
            flow_features=self._flow_features(out),
        )
        return self._result(out, new_state.frames_used), new_state

    def _first_step(self, frame: np.ndarray, pose: np.ndarray) -> tuple[StepResult, StreamState]:
        T = self.config.num_frames
        poses = (pose,) * T
        zero_flows = (self._zero_flow,) * (T - 2)
        zero_flow_features = (self._zero_flow_features,) if self.flow_cache else ()
        first = self._run_step(frame, poses, (self._zero_features,) * (T - 1), zero_flows, zero_flow_features)
        features, flow_features = (_frozen(first["features"][0]),) * (T - 1), self._flow_features(first)
        out = self._run_step(frame, poses, features, zero_flows, flow_features)
        flows: tuple[np.ndarray, ...] = ()
        if T > 2:  # the self-pair flow S1 fills the flow caches; rerun with them
            flows = (_frozen(out["flow"][0, -1].copy()),) * (T - 2)
            out = self._run_step(frame, poses, features, flows, flow_features)
        new_state = StreamState(
            frames_used=1, poses=poses[1:], features=features, flows=flows, flow_features=flow_features
        )
        return self._result(out, 1), new_state

    def _flow_features(self, out: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        return (_frozen(out["flow_features"][0]),) if self.flow_cache else ()

    def _run_step(
        self,
        frame: np.ndarray,
        poses: tuple[np.ndarray, ...],
        features: tuple[np.ndarray, ...],
        flows: tuple[np.ndarray, ...],
        flow_features: tuple[np.ndarray, ...] = (),
    ) -> dict[str, np.ndarray]:
        return self.run(self._feeds(frame, poses, features, flows, flow_features))

    def _feeds(
        self,
        frame: np.ndarray,
        poses: tuple[np.ndarray, ...],
        features: tuple[np.ndarray, ...],
        flows: tuple[np.ndarray, ...],
        flow_features: tuple[np.ndarray, ...] = (),
    ) -> dict[str, np.ndarray]:
        feeds = {
            "frame": frame[None, None],
            "poses": poses_in_newest_frame(np.stack(poses))[None],
            "past_features": np.stack(features)[None],
        }
        if flows:
            feeds["past_flows"] = np.stack(flows)[None]
        if flow_features:
            feeds["past_flow_features"] = flow_features[0][None]
        return feeds

    # ------------------------------------------------------------------ window form
    def _step_window(self, state: StreamState, frame: np.ndarray, pose: np.ndarray) -> tuple[StepResult, StreamState]:
        T = self.config.num_frames
        frame = _frozen(frame.copy())  # the state keeps it
        if state.frames_used == 0:
            frames, poses = (frame,) * T, (pose,) * T
        else:
            frames, poses = state.frames + (frame,), state.poses + (pose,)
        out = self.run(
            {"frames": np.stack(frames)[None, :, None], "poses": poses_in_newest_frame(np.stack(poses))[None]}
        )
        new_state = StreamState(frames_used=min(state.frames_used + 1, T), poses=poses[1:], frames=frames[1:])
        return self._result(out, new_state.frames_used), new_state

    # ------------------------------------------------------------------ outputs
    def _result(self, out: dict[str, np.ndarray], frames_used: int) -> StepResult:
        flow = out.get("flow")
        return StepResult(
            heatmap=out["heatmap"][0, 0],
            boxes=out["boxes"][0],
            scores=out["scores"][0],
            flow=None if flow is None else flow[0],
            frames_used=frames_used,
        )
