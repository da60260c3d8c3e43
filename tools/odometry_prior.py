"""The service's odometry per frame, side by side: registering every pair from scratch (estimate_relative_pose, what
the service ran before issue 30) against the stream's OdometryStream (each scan prepared once, the previous pair's
motion as the prior: what it runs now).

    python -m tools.odometry_prior SEQUENCE [--rounds 5]

SEQUENCE: any folder rafd's reader takes (RADIATE, Oxford/Boreas native, simulated). Each frame's odometry view is
what the service registers: the centre 512 px of the scan (service/body/images.py). Rounds alternate the two ways;
prints each way's median ms per frame over all frames and rounds. Torch-free.
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2

from rafd import progress
from rafd.cli import flags
from rafd.data import read_sequence
from rafd.odometry.registration import OdometryStream, estimate_relative_pose
from rafd.preprocess import model_crop
from service.body.images import ODOMETRY_VIEW_SIZE


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.odometry_prior", description=__doc__.splitlines()[0])
    parser.add_argument("sequence", help="a sequence folder")
    flags.add_count(parser, "--rounds", 5, 100, "rounds over the sequence")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    cv2.setNumThreads(1)  # as the service runs it: one opencv thread per worker
    sequence = read_sequence(args.sequence, estimate_poses=False)
    views, stamps = [], []
    for frame in sequence.frames:
        scan = frame.load()
        views.append(model_crop(scan, min(ODOMETRY_VIEW_SIZE, scan.shape[0])))
        stamps.append(frame.timestamp)
    if len(views) < 3:
        parser.error(f"{args.sequence}: {len(views)} frames; needs 3 or more")
    resolution = sequence.resolution
    pairwise_ms: list[float] = []
    stream_ms: list[float] = []
    for _ in progress.track(range(args.rounds), desc="odometry rounds", unit="round"):
        for previous, current in zip(views[:-1], views[1:]):
            start = time.perf_counter()
            estimate_relative_pose(previous, current, resolution)
            pairwise_ms.append(1000.0 * (time.perf_counter() - start))
        stream = OdometryStream(resolution)
        stream.add(views[0], stamps[0])
        for view, stamp in zip(views[1:], stamps[1:]):
            start = time.perf_counter()
            stream.add(view, stamp)
            stream_ms.append(1000.0 * (time.perf_counter() - start))
    side = views[0].shape[0]
    print(f"{len(views) - 1} frames x {args.rounds} rounds, {side} px views, opencv 1 thread")
    print(f"pairwise (each pair from scratch): median {statistics.median(pairwise_ms):.1f} ms per frame")
    print(f"stream (each scan prepared once):  median {statistics.median(stream_ms):.1f} ms per frame")
    print(f"ratio: {statistics.median(pairwise_ms) / statistics.median(stream_ms):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
