"""Two exported step graphs side by side: onnxruntime fp32 and OpenVINO fp32 on one thread, interleaved calls.

    python -m tools.compare_steps OLD.onnx NEW.onnx [--rounds 40]

Each round calls every (runtime, model) once in turn, so both models see the same machine load; prints the median
ms per step of each and NEW / OLD per runtime. The inputs are the graphs' own (a batch of one on a dynamic axis):
a frame and caches of uniform noise, identity poses. Speed only: the weights and values do not change the work.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rafd.cli import flags


def _feeds(inputs: list[Any]) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    feeds = {}
    for item in inputs:
        shape = [1 if not isinstance(d, int) else d for d in item.shape]
        scale = 0.0 if item.name == "poses" else 0.3
        feeds[item.name] = (rng.random(shape) * scale).astype(np.float32)
    return feeds


def step_callables(path: Path) -> dict[str, Callable[[], object]]:
    """-> {"onnxruntime": call, "openvino": call} (openvino only when installed), each one step on one thread."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    feeds = _feeds(session.get_inputs())
    calls: dict[str, Callable[[], object]] = {"onnxruntime": lambda: session.run(None, feeds)}
    try:
        import openvino as ov
    except ImportError:
        return calls
    core = ov.Core()
    model = core.read_model(str(path))
    model.reshape({i.get_any_name(): ov.PartialShape(list(feeds[i.get_any_name()].shape)) for i in model.inputs})
    hints = {"INFERENCE_NUM_THREADS": 1, "INFERENCE_PRECISION_HINT": "f32", "NUM_STREAMS": 1}
    request = core.compile_model(model, "CPU", hints).create_infer_request()
    calls["openvino"] = lambda: request.infer(feeds)
    return calls


def compare(old: Path, new: Path, rounds: int) -> dict[str, tuple[float, float]]:
    """-> {runtime: (old median ms, new median ms)}."""
    calls = {name: step_callables(path) for name, path in (("old", old), ("new", new))}
    runtimes = [r for r in calls["old"] if r in calls["new"]]
    times: dict[tuple[str, str], list[float]] = {(m, r): [] for m in calls for r in runtimes}
    for model, runtime in times:
        for _ in range(3):  # warm-up
            calls[model][runtime]()
    for _ in range(rounds):
        for model, runtime in times:
            start = time.perf_counter()
            calls[model][runtime]()
            times[(model, runtime)].append(1000.0 * (time.perf_counter() - start))
    return {r: (statistics.median(times[("old", r)]), statistics.median(times[("new", r)])) for r in runtimes}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.compare_steps", description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path, help="the step graph to compare against (.onnx)")
    parser.add_argument("new", type=Path, help="the step graph compared (.onnx)")
    flags.add_count(parser, "--rounds", 40, 1000, "interleaved rounds")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    for path in (args.old, args.new):
        if not path.is_file():
            parser.error(f"{path} is not a file")
    for runtime, (old_ms, new_ms) in compare(args.old, args.new, args.rounds).items():
        print(
            f"{runtime} fp32, 1 thread: {args.old.name} {old_ms:.2f} ms, {args.new.name} {new_ms:.2f} ms, "
            f"new / old {new_ms / old_ms:.3f} (medians of {args.rounds} interleaved rounds)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
