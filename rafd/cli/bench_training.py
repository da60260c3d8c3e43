"""`rafd-bench-training`: what training at RADIATE scale costs (rafd.bench.training)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from rafd.bench.training import __doc__ as DESCRIPTION
from rafd.bench.training import run_loader, run_precision
from rafd.cli.common import renamed


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rafd-bench-training", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    loader = commands.add_parser("loader", help="odometry, prepare and windows per second per worker")
    loader.add_argument("--work", type=Path, help="folder for the simulated root and cache (default: a temp dir)")
    loader.add_argument("--sequences", type=int, default=3)
    loader.add_argument("--frames", type=int, default=40)
    loader.add_argument("--windows", type=int, default=300, help="windows timed per configuration")
    loader.add_argument(
        "--workers",
        type=lambda t: [int(v) for v in t.split(",")],
        default=[1, 2],
        help="DataLoader worker counts to time (comma list)",
    )
    loader.add_argument("--prepare-workers", type=int, default=2, help="processes for rafd-odometry / rafd-prepare")
    precision = commands.add_parser("precision", help="fp32 vs bf16 step time and loss curves")
    precision.add_argument("--steps", type=int, default=5, help="timed steps per configuration and precision")
    precision.add_argument("--curve-steps", type=int, default=100, help="steps of the loss-curve runs")
    precision.add_argument("--threads", type=int, default=2)
    precision.add_argument("--json", type=Path, help="write the two loss curves here")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.command == "loader":
        return run_loader(args.work, args.sequences, args.frames, args.windows, args.workers, args.prepare_workers)
    return run_precision(args.steps, args.curve_steps, args.threads, args.json)


legacy_main = renamed("rafd-train-bench", "rafd-bench-training", main)


if __name__ == "__main__":
    sys.exit(main())
