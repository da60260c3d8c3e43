"""rafd-odometry: estimate ego poses from a sequence's radar scans and write ego_poses.csv.

    rafd-odometry SEQ_DIR [--out CSV] [--force]      write SEQ_DIR/ego_poses.csv (or CSV)
    rafd-odometry SEQ_DIR... --evaluate               compare with each SEQ_DIR/ego_poses.csv (e.g. the
                                                      simulator's true poses): per-pair translation (m) and
                                                      yaw (deg) errors and ms per pair; writes nothing

Exit status 0 on success, 2 on bad input (missing or malformed folder, existing output without --force).
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from rafd.data.poses import POSES_FILE, read_ego_poses, write_ego_poses
from rafd.data.reader import list_frames, load_image
from rafd.geometry import compose_poses, relative_pose, wrap_angle
from rafd.odometry import estimate_relative_pose


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rafd-odometry",
        description="Radar odometry: estimate the ego motion between consecutive scans of RADIATE-format sequences.",
    )
    parser.add_argument("seq_dirs", nargs="+", type=Path, metavar="SEQ_DIR", help="sequence folder(s) (Navtech_Cartesian/ + .txt)")
    parser.add_argument("--out", type=Path, help=f"output CSV (default SEQ_DIR/{POSES_FILE}; one SEQ_DIR only)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")
    parser.add_argument(
        "--evaluate", action="store_true",
        help=f"compare the estimates with each SEQ_DIR/{POSES_FILE} (true poses) and print error statistics; writes nothing",
    )
    return parser


def _fail(message: str) -> int:
    print(f"rafd-odometry: error: {message}", file=sys.stderr)
    return 2


def _estimate(seq_dir: Path) -> tuple[list[int], list[str], np.ndarray, np.ndarray, list[float]]:
    """-> (frame numbers, timestamps as written, world poses [N, 3], relative poses [N-1, 3], seconds per pair)."""
    listing = list_frames(seq_dir)
    relatives, seconds = [], []
    previous = load_image(listing.image_paths[0])
    for path in listing.image_paths[1:]:
        current = load_image(path)
        start = time.perf_counter()
        relatives.append(estimate_relative_pose(previous, current, listing.resolution))
        seconds.append(time.perf_counter() - start)
        previous = current
    poses = [np.zeros(3)]
    for relative in relatives:
        poses.append(compose_poses(poses[-1], relative))
    return listing.numbers, listing.timestamp_texts, np.stack(poses), np.array(relatives).reshape(-1, 3), seconds


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


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, estimate, write or evaluate; 0 on success, 2 on bad input."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.out is not None and (len(args.seq_dirs) > 1 or args.evaluate):
        return _fail("--out takes one SEQ_DIR and is not used with --evaluate")
    for seq_dir in args.seq_dirs:
        if not seq_dir.is_dir():
            return _fail(f"SEQ_DIR {seq_dir} is not a directory")
    if not args.evaluate:
        if len(args.seq_dirs) > 1:
            return _fail("give one SEQ_DIR to write poses (several only with --evaluate)")
        out = args.out or args.seq_dirs[0] / POSES_FILE
        if out.exists() and not args.force:
            return _fail(f"{out} exists; pass --force to overwrite it")
        if not out.parent.is_dir():
            return _fail(f"folder of --out does not exist: {out.parent}")
    all_translation, all_yaw, all_seconds = [], [], []
    for seq_dir in args.seq_dirs:
        try:
            numbers, stamps, poses, relatives, seconds = _estimate(seq_dir)
            if len(numbers) < 2:
                return _fail(f"{seq_dir} has {len(numbers)} frame(s); odometry needs at least 2")
            if args.evaluate:
                translation, yaw = _errors(seq_dir, numbers, relatives)
        except (FileNotFoundError, ValueError) as error:
            return _fail(str(error))
        if args.evaluate:
            print(_summary(str(seq_dir), translation, yaw, seconds))
            all_translation.append(translation)
            all_yaw.append(yaw)
            all_seconds += seconds
            continue
        try:
            write_ego_poses(out, numbers, stamps, poses)
        except OSError as error:
            return _fail(f"cannot write {out}: {error}")
        print(f"wrote {out}: {len(numbers)} poses, {1e3 * np.mean(seconds):.1f} ms per pair, "
              f"path length {np.hypot(*relatives[:, :2].T).sum():.1f} m")
    if args.evaluate and len(args.seq_dirs) > 1:
        print(_summary("all", np.concatenate(all_translation), np.concatenate(all_yaw), all_seconds))
    return 0


if __name__ == "__main__":
    sys.exit(main())
