"""rafd bench training: what training at RADIATE scale costs (bench.training)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from bench.training import __doc__ as DESCRIPTION
from bench.training import run_loader, run_precision
from rafd.cli import flags


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("bench training"), description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="{loader,precision}")
    loader = commands.add_parser("loader", help="odometry, prepare and windows per second per worker")
    loader.add_argument("--work", type=Path, help="folder for the simulated root and cache (default: a temp dir)")
    loader.add_argument("--sequences", type=int, default=3, help="simulated sequences (default 3)")
    flags.add_sequence_frames(loader, 40)
    loader.add_argument("--windows", type=int, default=300, help="windows timed per configuration")
    loader.add_argument(
        "--workers",
        type=flags.int_list,
        default=[1, 2],
        metavar="N[,N...]",
        help="parallel worker processes: the DataLoader worker counts to time, a comma list (default 1,2)",
    )
    loader.add_argument("--prepare-workers", type=int, default=2, help="processes for rafd odometry / rafd prepare")
    flags.add_quiet(loader)
    precision = commands.add_parser("precision", help="fp32 vs bf16 step time and loss curves")
    precision.add_argument("--steps", type=int, default=5, help="timed steps per configuration and precision")
    precision.add_argument("--curve-steps", type=int, default=100, help="steps of the loss-curve runs")
    flags.add_threads(precision, 2, "torch's CPU threads (default 2)")
    precision.add_argument("--json", type=Path, metavar="FILE", help="write the two loss curves here")
    flags.add_quiet(precision)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.command == "loader":
        return run_loader(args.work, args.sequences, args.frames, args.windows, args.workers, args.prepare_workers)
    return run_precision(args.steps, args.curve_steps, args.threads, args.json)


if __name__ == "__main__":
    sys.exit(main())
