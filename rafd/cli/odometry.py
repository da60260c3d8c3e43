"""rafd odometry: prepare ego poses by radar odometry for every sequence of a data root (ego_poses.csv).

Writes ego_poses.csv into every sequence folder at or under each ROOT that has none, in parallel processes
(resumable: run it again after an interruption; --force re-estimates). With one sequence, --out CSV writes its poses
elsewhere. --evaluate compares the estimates with each sequence's ego_poses.csv (e.g. the simulator's true poses):
per-pair translation (m) and yaw (deg) errors and ms per pair; it writes nothing.

Training and evaluation never run odometry themselves (unless asked: `rafd eval --estimate-poses`, `rafd train ...
data.estimate_poses=true`): prepare once here.
Exit status 0 on success, 2 on bad input, 1 when a sequence failed (the others are still written).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from rafd.cli import flags
from rafd.cpu import usable_cpus
from rafd.data.dataset import select_sequences
from rafd.data.ego_motion import consecutive_pairs, error_summary, estimate, signed_errors, write_poses
from rafd.data.poses import POSES_FILE
from rafd.progress import track
from rafd.ros.sequence import is_bag, poses_file


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("odometry"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "roots",
        nargs="+",
        type=Path,
        metavar="ROOT",
        help="data root(s) or sequence folder(s) (Navtech_Cartesian/ + .txt), or ROS 2 bags (poses written beside "
        "the bag as BAG.ego_poses.csv)",
    )
    flags.add_split(parser, "only sequences of these splits")
    flags.add_workers(parser, usable_cpus(), "sequences estimated at once (default: the CPUs)")
    flags.add_out(parser, "CSV", f"the poses of one sequence to this CSV (default SEQ_DIR/{POSES_FILE})")
    parser.add_argument("--force", action="store_true", help="re-estimate sequences that already have poses")
    parser.add_argument(
        "--evaluate",
        action="store_true",
        help=f"compare the estimates with each sequence's true poses ({POSES_FILE}, or a native folder's ground-truth "
        "odometry) and print error statistics over the pairs one scan period apart; writes nothing",
    )
    parser.add_argument(
        "--per-pair",
        action="store_true",
        help="with --evaluate: also print every pair's signed error (x right, y forward, yaw CCW)",
    )
    flags.add_quiet(parser)
    return parser


def _fail(message: str) -> int:
    print(f"rafd-odometry: error: {message}", file=sys.stderr)
    return 2


def _evaluate(folders: list[Path], per_pair: bool) -> int:
    all_translation, all_yaw, all_seconds = [], [], []
    for seq_dir in track(folders, desc="odometry evaluated", unit="seq"):
        try:
            numbers, stamps, _, relatives, seconds = estimate(seq_dir)
            error = signed_errors(seq_dir, numbers, relatives)
        except (FileNotFoundError, ValueError) as failure:
            return _fail(str(failure))
        keep = consecutive_pairs(stamps)  # a pair across a gap in the recording is not one scan's step
        if per_pair:
            for k, (dx, dy, dyaw) in enumerate(error.tolist(), 1):
                gap = "" if keep[k - 1] else "  (across a gap: not in the summary)"
                print(
                    f"{seq_dir} frames {numbers[k - 1]}-{numbers[k]}: error x {dx:+.3f} m, y {dy:+.3f} m, "
                    f"yaw {np.rad2deg(dyaw):+.3f} deg{gap}"
                )
        translation, yaw = np.hypot(error[keep, 0], error[keep, 1]), np.abs(np.rad2deg(error[keep, 2]))
        seconds = list(np.asarray(seconds)[keep])
        print(error_summary(str(seq_dir), translation, yaw, seconds))
        all_translation.append(translation)
        all_yaw.append(yaw)
        all_seconds += seconds
    if len(folders) > 1:
        print(error_summary("all", np.concatenate(all_translation), np.concatenate(all_yaw), all_seconds))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, then prepare (in parallel) or evaluate; 0 on success, 2 on bad input, 1 on failures."""
    args = _parser().parse_args(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.workers < 1:
        return _fail("--workers must be >= 1")
    folders: list[Path] = []
    for root in args.roots:
        if not root.is_dir() and not is_bag(root):
            return _fail(f"{root} is not a directory or a bag")
        try:
            chosen, _ = select_sequences(root, list(flags.split_names(args.split)) or None)
        except (FileNotFoundError, ValueError) as error:
            return _fail(str(error))
        folders += chosen
    if not folders:
        return _fail(f"no sequence of split {args.split} under {', '.join(map(str, args.roots))}")
    if args.evaluate:
        if args.out is not None:
            return _fail("--out is not used with --evaluate")
        return _evaluate(folders, args.per_pair)
    if args.out is not None:
        if len(folders) != 1:
            return _fail(f"--out takes one sequence, found {len(folders)}")
        if not args.out.parent.is_dir():
            return _fail(f"folder of --out does not exist: {args.out.parent}")
    start = time.perf_counter()
    results, failures = write_poses(folders, args.workers, args.force, args.out)
    counts, frames = {"written": 0, "skipped": 0}, 0
    for folder, (status, count, ms_per_pair) in results:
        counts[status] += 1
        frames += count
        if status == "written" and len(folders) == 1:
            written = args.out or (poses_file(folder) if is_bag(folder) else folder / POSES_FILE)
            print(f"wrote {written}: {count} poses, {ms_per_pair:.1f} ms per pair")
    seconds = time.perf_counter() - start
    print(
        f"{counts['written']} sequences given poses ({frames} frames in {seconds:.1f} s), "
        f"{counts['skipped']} already had {POSES_FILE} (--force re-estimates them)"
    )
    for failure in failures:
        print(f"rafd-odometry: error: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
