"""rafd prepare: decode every scan of a data root once into memory-mapped centre crops (rafd.data.cache).

Training and evaluation then read windows from the cache (`rafd train --cache CACHE`, `rafd eval --cache CACHE`)
instead of decoding four full 1152 px PNGs per window. Sequences are prepared in parallel processes; a sequence
whose cache is complete (CACHE/<sequence>/cache.json) and matches its frames is skipped, so an interrupted run is
resumed by running the same command again. Exit status 0 on success, 2 on bad input, 1 if a sequence failed.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from rafd.cli import flags
from rafd.cpu import usable_cpus
from rafd.data.cache import DEFAULT_CROP
from rafd.data.prepare import prepare_root


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("prepare"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "root", type=Path, metavar="ROOT", help="data root holding RADIATE sequence folders (or one sequence)"
    )
    flags.add_out(parser, "CACHE", "cache root to write (mirrors the sequence folders)", required=True)
    flags.add_split(parser, "only sequences of these splits")
    parser.add_argument(
        "--crop-size",
        type=int,
        default=DEFAULT_CROP,
        metavar="PX",
        help=f"side in pixels of the cached centre crop (default {DEFAULT_CROP}: a 256 px input turned by any angle)",
    )
    flags.add_workers(parser, usable_cpus(), "sequences prepared at once (default: the CPUs)")
    parser.add_argument("--force", action="store_true", help="rebuild complete caches too")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        split = list(flags.split_names(args.split)) or None
        done = prepare_root(args.root, args.out, split, args.crop_size, args.workers, args.force)
    except (FileNotFoundError, ValueError) as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 2
    print(
        f"{args.out}: {done.prepared} sequences prepared ({done.frames} frames, "
        f"{done.frames / max(done.seconds, 1e-9):.0f} frames/s), {done.skipped} already complete, in "
        f"{done.seconds:.1f} s"
    )
    for failure in done.failures:
        print(f"{parser.prog}: error: {failure}", file=sys.stderr)
    return 1 if done.failures else 0


if __name__ == "__main__":
    sys.exit(main())
