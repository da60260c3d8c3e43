"""What a whole scan's model step would cost with a changed network, before anyone trains it: the shipped model's
config and each variant (model config settings) built with random weights, exported as the service's step graph
(dynamic batch) and stepped by the service's onnxruntime fp32 runner on one thread, a started stream of a whole
scan's tiles (21 for a 1152 px RADIATE scan), in interleaved rounds; prints the median ms per scan and its ratio to
the shipped config's.

    python -m bench.network_cost --variant "neck.channels=16" --variant "neck.channels=16 enhance.num_blocks=1"

Random weights cost what trained ones do (no operation's time depends on the values). Wall time of one thread: run
it on an otherwise idle machine and compare ratios within one run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rafd.cli import flags

if TYPE_CHECKING:
    from rafd.config import RaFDConfig
    from rafd.runtime import OnnxRunner
    from rafd.runtime.streaming import StreamState

WHOLE_SCAN_TILES = 21  # rafd.runtime.view: a 1152 px scan's tiles whose centre lies in the radar's circle


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.network_cost", description=__doc__)
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="'KEY=VALUE ...'",
        help="model config settings of one variant, space-separated (e.g. 'neck.channels=16'); repeatable",
    )
    parser.add_argument("--tiles", type=int, default=WHOLE_SCAN_TILES, help="batch of tiles per scan (default 21)")
    parser.add_argument("--rounds", type=int, default=11, help="interleaved rounds (default 11)")
    flags.add_checkpoint(parser, nargs="?", what="its config is the base (default: the shipped model's)")
    return parser


def stream_runner(cfg: RaFDConfig, folder: Path) -> tuple[OnnxRunner, int]:
    """A random-weight model of `cfg` exported as the service's step graph, in the service's onnxruntime runner on
    one thread -> (runner, parameters)."""
    from export.onnx_export import export_onnx
    from rafd.model.build import build_model, count_parameters
    from rafd.model.checkpoint import save_checkpoint
    from rafd.runtime import OnnxRunner

    model = build_model(cfg).eval()
    checkpoint = folder / "model.pt"
    save_checkpoint(checkpoint, model, cfg, {})
    exported = export_onnx(checkpoint, folder / "model.onnx", verify=False, log=lambda _: None)
    return OnnxRunner(exported.path, threads=1), count_parameters(model)


def started_stream(runner: OnnxRunner, tiles: int) -> tuple[StreamState, np.ndarray, np.ndarray]:
    """A stream of `tiles` views past its warm-up (random frames, no motion) -> (its state, a frame, the poses)."""
    rng = np.random.default_rng(0)
    size = runner.config.input_size
    frames = rng.random((tiles, size, size), dtype=np.float32)
    poses = np.zeros((tiles, 3))
    state = runner.new_state()
    for _ in range(runner.config.num_frames):
        state = runner.step(state, frames, poses)[1]
    return state, frames, poses


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from rafd.assets import default_checkpoint
    from rafd.config_tree import overridden, parse_overrides
    from rafd.model.checkpoint import read_checkpoint

    base = read_checkpoint(args.checkpoint or default_checkpoint())[1]
    variants = {"shipped": base}
    try:
        for text in args.variant:
            variants[text] = overridden(base, parse_overrides(text.split()))
    except ValueError as error:
        print(f"network_cost: error: {error}", file=sys.stderr)
        return 2
    runs: dict[str, tuple[OnnxRunner, tuple[StreamState, np.ndarray, np.ndarray], int, list[float]]] = {}
    with tempfile.TemporaryDirectory(prefix="rafd-network-cost-") as tmp:
        for index, (name, cfg) in enumerate(variants.items()):
            folder = Path(tmp, str(index))
            folder.mkdir()
            runner, parameters = stream_runner(cfg, folder)
            runs[name] = (runner, started_stream(runner, args.tiles), parameters, [])
        for _ in range(args.rounds):
            for runner, (state, frames, poses), _, times in runs.values():
                start = time.perf_counter()
                runner.step(state, frames, poses)
                times.append(time.perf_counter() - start)
    reference = statistics.median(runs["shipped"][3])
    print(f"onnxruntime fp32, one thread, {args.tiles} tiles per scan, median of {args.rounds} interleaved rounds")
    for name, (_, _, parameters, times) in runs.items():
        median = statistics.median(times)
        print(f"{name:48s} {parameters:8d} parameters {1000 * median:8.1f} ms per scan {median / reference:6.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
