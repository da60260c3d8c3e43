"""The exported step graph's interface, as the runtime sees it: what goes in, what comes out, what it carries.

    inputs   frame [B, 1, S, S] float32 in [0, 1]; pose [B, 3] (this frame's pose in the previous frame's ego frame:
             rafd.geometry.relative_pose(current, previous), float32; zeros on a stream's first frame);
             cache.NAME ... (the model's state: zeros on a stream's first frame)
    outputs  heatmap [B, 1, Hf, Wf], scores [B, K], boxes [B, K, 5], flow [B, 2, Hf, Wf] (multi-frame models),
             frames_used [B]; new_cache.NAME ... of the shapes of cache.NAME, fed back as cache.NAME next step

What the cache holds, how it rolls and how a stream warms up are the model's (rafd.model.RaFD.step): a runtime only
carries new_cache.NAME to the next step's cache.NAME.
"""

from __future__ import annotations

CACHE_PREFIX = "cache."
NEW_CACHE_PREFIX = "new_cache."
STEP_INPUTS = ("frame", "pose")
STEP_OUTPUTS = ("heatmap", "scores", "boxes", "flow", "frames_used")
METADATA_KEYS = (
    "config",
    "input_size",
    "resolution",
    "num_frames",
    "class_names",
    "checkpoint_sha256",
    "version",
)


def cache_names(input_names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The cache inputs of a graph (cache.NAME), in graph order."""
    return tuple(name for name in input_names if name.startswith(CACHE_PREFIX))


def carried(name: str) -> str:
    """The output a cache input is fed from: cache.NAME <- new_cache.NAME."""
    return NEW_CACHE_PREFIX + name[len(CACHE_PREFIX) :]


def check_step_graph(
    where: str, input_shapes: dict[str, tuple[int, ...]], output_names: tuple[str, ...], num_frames: int
) -> None:
    """ValueError naming what is wrong when a graph does not follow the step contract."""
    problems = []
    inputs = tuple(input_shapes)
    if inputs[:2] != STEP_INPUTS:
        problems.append(f"its first inputs are {inputs[:2]}, not {STEP_INPUTS}")
    others = [name for name in inputs[2:] if not name.startswith(CACHE_PREFIX)]
    if others:
        problems.append(f"inputs {others} are neither {STEP_INPUTS} nor {CACHE_PREFIX}*")
    needed = [n for n in STEP_OUTPUTS if n != "flow" or num_frames > 1]
    needed += [carried(name) for name in cache_names(inputs)]
    missing = [name for name in needed if name not in output_names]
    if missing:
        problems.append(f"outputs {missing} are missing")
    if problems:
        raise ValueError(
            f"{where} is not a RaFD step graph: {'; '.join(problems)} (inputs {inputs}, outputs {output_names})"
        )
