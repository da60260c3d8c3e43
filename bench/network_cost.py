"""What a whole scan's model step would cost with a changed network, before anyone trains it: the shipped model's
config and each variant (model config settings) built with random weights, exported as the service's step graph
(dynamic batch) and run by onnxruntime fp32 on one thread at a whole scan's batch of tiles (21 for a 1152 px RADIATE
scan), in interleaved rounds; prints the median ms per scan and its ratio to the shipped config's.

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
    import onnxruntime as ort

    from rafd.config import RaFDConfig

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


def step_session(cfg: RaFDConfig, folder: Path) -> tuple[ort.InferenceSession, int]:
    """A random-weight model of `cfg` as the service's step graph in onnxruntime, one thread -> (session, params)."""
    import onnxruntime as ort

    from export.onnx_export import export_onnx
    from rafd.model.build import build_model, count_parameters
    from rafd.model.checkpoint import save_checkpoint

    model = build_model(cfg).eval()
    checkpoint = folder / "model.pt"
    save_checkpoint(checkpoint, model, cfg, {})
    exported = export_onnx(checkpoint, folder / "model.onnx", verify=False, log=lambda _: None)
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(exported.path), options, providers=["CPUExecutionProvider"])
    return session, count_parameters(model)


def scan_feeds(session: ort.InferenceSession, tiles: int) -> dict[str, np.ndarray]:
    """Inputs of a started stream's step over `tiles` tiles: random frames and cache, no motion."""
    rng = np.random.default_rng(0)
    feeds = {
        i.name: rng.random([tiles if isinstance(d, str) else d for d in i.shape], dtype=np.float32)
        for i in session.get_inputs()
    }
    for name in ("pose", "cache.poses"):
        if name in feeds:
            feeds[name][:] = 0.0
    if "cache.frames" in feeds:
        feeds["cache.frames"][:] = 3.0  # a started stream: the cache is used, not this frame's padding
    return feeds


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
    runs: dict[str, tuple[ort.InferenceSession, dict[str, np.ndarray], int, list[float]]] = {}
    with tempfile.TemporaryDirectory(prefix="rafd-network-cost-") as tmp:
        for index, (name, cfg) in enumerate(variants.items()):
            folder = Path(tmp, str(index))
            folder.mkdir()
            session, parameters = step_session(cfg, folder)
            feeds = scan_feeds(session, args.tiles)
            session.run(None, feeds)  # warm-up
            runs[name] = (session, feeds, parameters, [])
        for _ in range(args.rounds):
            for session, feeds, _, times in runs.values():
                start = time.perf_counter()
                session.run(None, feeds)
                times.append(time.perf_counter() - start)
    reference = statistics.median(runs["shipped"][3])
    print(f"onnxruntime fp32, one thread, {args.tiles} tiles per scan, median of {args.rounds} interleaved rounds")
    for name, (_, _, parameters, times) in runs.items():
        median = statistics.median(times)
        print(f"{name:48s} {parameters:8d} parameters {1000 * median:8.1f} ms per scan {median / reference:6.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
