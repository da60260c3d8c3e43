"""Export + parity + CPU timing of onnxruntime vs PyTorch for the tiny and paper configs (random weights).

    python -m export.bench [--configs tiny paper] [--repeats 10] [--threads N] [--keep DIR]

Per config: export time and ONNX size of the step and window forms, the parity differences of each, and the
time (min and median) of one window forward (PyTorch model.forward vs onnxruntime window graph), of one streaming
step (PyTorch StepGraph vs rafd.runtime.OnnxRunner.step, steady state: caches full) and of a stream's first frame.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from export.onnx_export import export_onnx
from export.step import build_graph, feature_channels
from export.verify import random_sequence
from rafd.checkpoint import save_checkpoint
from rafd.config import RaFDConfig
from rafd.model import build_model
from rafd.runtime import OnnxRunner, default_threads, poses_in_newest_frame

CONFIGS = {"tiny": RaFDConfig.tiny, "paper": RaFDConfig.paper}


def time_interleaved(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, tuple[float, float]]:
    """-> {name: (min ms, median ms)}; the candidates alternate run by run so that load from other processes on a
    shared CPU hits them alike (the minimum is the least disturbed figure)."""
    for fn in fns.values():
        fn()  # first-run allocations
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append(1000.0 * (time.perf_counter() - start))
    return {name: (min(t), statistics.median(t)) for name, t in times.items()}


@torch.no_grad()
def bench_config(name: str, folder: Path, repeats: int, threads: int) -> list[str]:
    cfg = CONFIGS[name]()
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    checkpoint = save_checkpoint(folder / f"{name}.pt", model, cfg)
    lines = [f"== {name}: S={cfg.input_size} T={cfg.num_frames} K={cfg.head.num_queries} "
             f"params={sum(p.numel() for p in model.parameters()) / 1e6:.2f} M"]
    runners = {}
    for form in ("step", "window"):
        log: list[str] = []
        result = export_onnx(checkpoint, folder / f"{name}_{form}.onnx", form=form, log=log.append)
        lines.append(f"{form:6s} export {result.export_seconds:.1f} s ({result.exporter}), "
                     f"{result.size_bytes / 1e6:.1f} MB, verify {result.verify_seconds:.1f} s")
        lines += [f"   {line.strip()}" for line in result.report.lines()]
        runners[form] = OnnxRunner(result.path, threads=threads)

    T = cfg.num_frames
    frames, poses = random_sequence(cfg, T + 1, seed=1)
    window_frames = torch.from_numpy(frames[1:])[None, :, None]
    window_poses = torch.from_numpy(poses[1:].astype(np.float32))[None]
    feeds = {"frames": window_frames.numpy(), "poses": poses_in_newest_frame(poses[1:])[None]}

    step = build_graph(model, cfg, "step")
    channels = feature_channels(model, cfg)
    inputs = [torch.from_numpy(frames[-1])[None, None], window_poses]
    if T > 1:
        inputs.append(torch.randn(1, T - 1, channels, cfg.feature_size, cfg.feature_size))
    if T > 2:
        inputs.append(torch.randn(1, T - 2, 2, cfg.feature_size, cfg.feature_size))
    runner = runners["step"]
    state = runner.new_state()
    for frame, pose in zip(frames[:-1], poses[:-1]):  # caches full: the steady state of a stream
        _, state = runner.step(state, frame, pose)
    ms = time_interleaved({
        "torch window": lambda: model(window_frames, window_poses),
        "ort window": lambda: runners["window"].run(feeds),
        "torch step": lambda: step(*inputs),
        "ort step": lambda: runner.step(state, frames[-1], poses[-1]),
        "ort first frame": lambda: runner.step(runner.new_state(), frames[-1], poses[-1]),
    }, repeats)
    lines.append("timing, min / median ms: " + ", ".join(f"{k} {lo:.1f} / {med:.1f}" for k, (lo, med) in ms.items()))
    lines.append(f"window forward: onnxruntime x{ms['torch window'][0] / ms['ort window'][0]:.2f} vs PyTorch; "
                 f"streaming step: onnxruntime x{ms['torch step'][0] / ms['ort step'][0]:.2f} vs PyTorch; "
                 f"onnxruntime step x{ms['ort window'][0] / ms['ort step'][0]:.2f} faster than its window (min)")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=["tiny", "paper"])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None, help="torch and onnxruntime threads (default: affinity)")
    parser.add_argument("--keep", type=Path, default=None, help="write checkpoints and ONNX files here")
    args = parser.parse_args(argv)
    threads = args.threads or default_threads()
    torch.set_num_threads(threads)
    print(f"{threads} threads (torch and onnxruntime), torch {torch.__version__}, {args.repeats} runs each")
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.keep or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        for name in args.configs:
            for line in bench_config(name, folder, args.repeats, threads):
                print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
