"""rafd-odometry: prepare ego poses by radar odometry for every sequence of a data root (ego_poses.csv).

    rafd-odometry ROOT [ROOT ...] [--split NAME ...] [--workers N] [--force]
                                   write ego_poses.csv into every sequence folder at or under each ROOT that has
                                   none (resumable: run it again after an interruption), in parallel processes
    rafd-odometry SEQ_DIR --out CSV [--force]
                                   write one sequence's poses elsewhere
    rafd-odometry ROOT... --evaluate
                                   compare estimates with each sequence's ego_poses.csv (e.g. the simulator's true
                                   poses): per-pair translation (m) and yaw (deg) errors and ms per pair; writes nothing

Training and evaluation never run odometry themselves (unless asked with --estimate-poses): prepare once here.
Exit status 0 on success, 2 on bad input, 1 when a sequence failed (the others are still written).
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
from rafd.data.dataset import select_sequences
from rafd.data.poses import POSES_FILE, read_ego_poses, write_ego_poses
from rafd.data.reader import list_frames
from rafd.geometry import compose_poses, relative_pose, wrap_angle
from rafd.odometry import estimate_relative_pose


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-odometry", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("roots", nargs="+", type=Path, metavar="ROOT",
                        help="data root(s) or sequence folder(s) (Navtech_Cartesian/ + .txt)")
    parser.add_argument("--split", action="append", help="only sequences of these meta.json splits")
    parser.add_argument("--workers", type=int, default=default_workers(), help="parallel processes (default: CPUs)")
    parser.add_argument("--out", type=Path, help=f"output CSV (default SEQ_DIR/{POSES_FILE}; one sequence only)")
    parser.add_argument("--force", action="store_true", help="re-estimate sequences that already have poses")
    parser.add_argument(
        "--evaluate", action="store_true",
        help=f"compare the estimates with each sequence's {POSES_FILE} (true poses) and print error statistics; "
             "writes nothing",
    )
    return parser


def _fail(message: str) -> int:
    print(f"rafd-odometry: error: {message}", file=sys.stderr)
    return 2


def estimate(seq_dir: Path) -> tuple[list[int], list[str], np.ndarray, np.ndarray, list[float]]:
    """-> (frame numbers, canonical timestamp texts, world poses [N, 3], relative poses [N-1, 3], seconds per pair)."""
    listing = list_frames(seq_dir)
    if len(listing.numbers) < 2:
        raise ValueError(f"{seq_dir} has {len(listing.numbers)} frame(s); odometry needs at least 2")
    relatives, seconds = [], []
    previous = listing.load(0)
    for index in range(1, len(listing.numbers)):
        current = listing.load(index)  # a Cartesian scan (converted from the polar one in polar-only folders)
        start = time.perf_counter()
        relatives.append(estimate_relative_pose(previous, current, listing.resolution))
        seconds.append(time.perf_counter() - start)
        previous = current
    poses = [np.zeros(3)]
    for relative in relatives:
        poses.append(compose_poses(poses[-1], relative))
    return listing.numbers, listing.timestamp_texts, np.stack(poses), np.array(relatives).reshape(-1, 3), seconds


def prepare_poses(seq_dir: Path, out: Path | None, force: bool) -> tuple[str, int, float]:
    """Write one sequence's ego_poses.csv (atomically) -> (status "written" | "skipped", frames, ms per pair)."""
    out = out or seq_dir / POSES_FILE
    if out.exists() and not force:
        return "skipped", 0, 0.0
    numbers, stamps, poses, _, seconds = estimate(seq_dir)
    write_ego_poses(out, numbers, stamps, poses)
    return "written", len(numbers), 1e3 * float(np.mean(seconds))


def _errors(seq_dir: Path, numbers: list[int], relatives: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair (translation error m, yaw error deg) against SEQ_DIR/ego_poses.csv."""
    truth_table = read_ego_poses(seq_dir / POSES_FILE)
    missing = [n for n in numbers if n not in truth_table]
    if missing:
        raise ValueError(f"{seq_dir / POSES_FILE}: no pose for frame {missing[0]}")
    truth = np.stack([truth_table[n][1] for n in numbers])
    true_relatives = np.stack([relative_pose(truth[k], truth[k - 1]) for k in range(1, len(truth))]).reshape(-1, 3)
    translation = np.hypot(*(relatives[:, :2] - true_relatives[:, :2]).T)
    yaw = np.abs(np.rad2deg(wrap_angle(relatives[:, 2] - true_relatives[:, 2])))
    return translation, yaw


def _summary(label: str, translation: np.ndarray, yaw: np.ndarray, seconds: list[float]) -> str:
    return (
        f"{label}: {len(translation)} pairs | translation error m mean {translation.mean():.3f} "
        f"p95 {np.percentile(translation, 95):.3f} max {translation.max():.3f} | yaw error deg mean {yaw.mean():.3f} "
        f"p95 {np.percentile(yaw, 95):.3f} max {yaw.max():.3f} | {1e3 * np.mean(seconds):.1f} ms/pair"
    )


def _evaluate(folders: list[Path]) -> int:
    all_translation, all_yaw, all_seconds = [], [], []
    for seq_dir in folders:
        try:
            numbers, _, _, relatives, seconds = estimate(seq_dir)
            translation, yaw = _errors(seq_dir, numbers, relatives)
        except (FileNotFoundError, ValueError) as error:
            return _fail(str(error))
        print(_summary(str(seq_dir), translation, yaw, seconds))
        all_translation.append(translation)
        all_yaw.append(yaw)
        all_seconds += seconds
    if len(folders) > 1:
        print(_summary("all", np.concatenate(all_translation), np.concatenate(all_yaw), all_seconds))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, then prepare (in parallel) or evaluate; 0 on success, 2 on bad input, 1 on failures."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.workers < 1:
        return _fail("--workers must be >= 1")
    folders: list[Path] = []
    for root in args.roots:
        if not root.is_dir():
            return _fail(f"{root} is not a directory")
        try:
            chosen, _ = select_sequences(root, args.split)
        except (FileNotFoundError, ValueError) as error:
            return _fail(str(error))
        folders += chosen
    if not folders:
        return _fail(f"no sequence of split {args.split} under {', '.join(map(str, args.roots))}")
    if args.evaluate:
        if args.out is not None:
            return _fail("--out is not used with --evaluate")
        return _evaluate(folders)
    if args.out is not None:
        if len(folders) != 1:
            return _fail(f"--out takes one sequence, found {len(folders)}")
        if not args.out.parent.is_dir():
            return _fail(f"folder of --out does not exist: {args.out.parent}")
    start = time.perf_counter()
    job = functools.partial(prepare_poses, out=args.out, force=args.force)
    results, failures = run_per_sequence(job, folders, args.workers, "odometry", progress=len(folders) > 1)
    counts, frames = {"written": 0, "skipped": 0}, 0
    for folder, (status, count, ms_per_pair) in results:
        counts[status] += 1
        frames += count
        if status == "written" and len(folders) == 1:
            print(f"wrote {args.out or folder / POSES_FILE}: {count} poses, {ms_per_pair:.1f} ms per pair")
    seconds = time.perf_counter() - start
    print(f"{counts['written']} sequences given poses ({frames} frames in {seconds:.1f} s), "
          f"{counts['skipped']} already had {POSES_FILE} (--force re-estimates them)")
    for failure in failures:
        print(f"rafd-odometry: error: {failure}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
