"""rafd-prepare ROOT CACHE: decode every scan of a data root once into memory-mapped centre crops (rafd.data.cache).

    rafd-prepare ROOT CACHE [--split NAME ...] [--crop PX] [--workers N] [--force]

Training and evaluation then read windows from CACHE (`rafd-train --cache CACHE`, `rafd-eval --cache CACHE`)
instead of decoding four full 1152 px PNGs per window. Sequences are prepared in parallel processes; a sequence
whose cache is complete (CACHE/<sequence>/cache.json) and matches its frames is skipped, so an interrupted run is
resumed by running the same command again. Exit status 0 on success, 2 on bad input, 1 if a sequence failed.
"""
from __future__ import annotations

import argparse
import functools
import logging
import sys
import time
from pathlib import Path

import numpy as np

from rafd.cli.per_sequence import default_workers, run_per_sequence
from rafd.data.cache import DEFAULT_CROP, CacheError, cache_folder, read_cached, write_cached
from rafd.data.dataset import select_sequences
from rafd.data.reader import read_sequence

log = logging.getLogger("rafd.prepare")


def prepare_sequence(folder: Path, root: Path, cache_root: Path, crop: int, force: bool) -> tuple[str, int, float]:
    """Cache one sequence -> (status "prepared" | "skipped", frames, seconds)."""
    start = time.perf_counter()
    sequence = read_sequence(folder, estimate_poses=False)
    target = cache_folder(cache_root, root, folder)
    numbers = np.array([f.number for f in sequence.frames], np.int64)
    if not force:
        try:
            read_cached(target, numbers, sequence.image_size, min(crop, sequence.image_size))
            return "skipped", len(numbers), time.perf_counter() - start
        except CacheError:
            pass  # absent, incomplete or stale: (re)build it
    write_cached(target, (frame.load() for frame in sequence.frames), numbers.tolist(), crop, sequence.image_size,
                 folder)
    return "prepared", len(numbers), time.perf_counter() - start


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-prepare", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", type=Path, help="data root holding RADIATE sequence folders (or one sequence)")
    parser.add_argument("cache", type=Path, help="cache root to write (mirrors the sequence folders)")
    parser.add_argument("--split", action="append", help="only these meta.json splits (repeat or comma-separate)")
    parser.add_argument("--crop", type=int, default=DEFAULT_CROP,
                        help=f"centre crop side in pixels (default {DEFAULT_CROP}: a 256 px input turned by any angle)")
    parser.add_argument("--workers", type=int, default=default_workers(), help="parallel processes (default: CPUs)")
    parser.add_argument("--force", action="store_true", help="rebuild complete caches too")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.crop < 16 or args.crop % 2:
        print(f"rafd-prepare: error: --crop must be an even number of pixels >= 16, got {args.crop}", file=sys.stderr)
        return 2
    if args.workers < 1:
        print("rafd-prepare: error: --workers must be >= 1", file=sys.stderr)
        return 2
    try:
        folders, seen = select_sequences(args.root, args.split)
    except (FileNotFoundError, ValueError) as error:
        print(f"rafd-prepare: error: {error}", file=sys.stderr)
        return 2
    if not folders:
        print(f"rafd-prepare: error: no sequence of split {args.split} under {args.root} (splits: {seen})",
              file=sys.stderr)
        return 2
    args.cache.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    job = functools.partial(prepare_sequence, root=args.root, cache_root=args.cache, crop=args.crop, force=args.force)
    results, failures = run_per_sequence(job, folders, args.workers, "prepare")
    counts = {"prepared": 0, "skipped": 0}
    frames = 0
    for _, (status, count, _) in results:
        counts[status] += 1
        frames += count if status == "prepared" else 0
    seconds = time.perf_counter() - start
    print(f"{args.cache}: {counts['prepared']} sequences prepared ({frames} frames, {frames / max(seconds, 1e-9):.0f} "
          f"frames/s), {counts['skipped']} already complete, in {seconds:.1f} s")
    for failure in failures:
        print(f"rafd-prepare: error: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
