"""The service's odometry against a baseline copy of it, side by side: accuracy and CPU per frame.

    git show REV:rafd/odometry/registration.py > /tmp/odometry_old.py
    python -m tools.odometry_cost SEQUENCE... [--baseline /tmp/odometry_old.py] [--rounds 2]

Each SEQUENCE (a simulated drive, the Oxford sample, any folder rafd's reader takes) is run as the service runs a
stream posted without poses: `OdometryStream.add` on the centre 512 px of each scan (service/body/images.py), with the
scan's own azimuth timestamps for native scans, opencv on one thread. Prints, per way, the error against the
folder's true poses over the pairs one scan apart (ego_poses.csv, or a native folder's ground truth; pairs across a
recording gap left out: the stream starts again there, as the service restarts a stream's chain after a gap of more
than RAFD_STREAM_GAP_RESTART_S) and the thread's CPU time per frame (median, mean, and the median of the streams' first
pairs). Accuracy is deterministic; CPU rounds interleave the ways per sequence, so both share the machine's noise.
Torch-free.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np

import rafd.odometry.registration as this_odometry
from rafd import progress
from rafd.cli import flags
from rafd.data import read_sequence
from rafd.data.ego_motion import consecutive_pairs, scan_and_timing
from rafd.data.folders import list_frames
from rafd.geometry import relative_pose, wrap_angle
from rafd.odometry.registration import SweepTiming
from rafd.preprocess import model_crop
from service.body.images import ODOMETRY_VIEW_SIZE


@dataclass
class Drive:
    views: list[np.ndarray]  # [V, V] uint8 centre of each scan
    stamps: list[float]
    timings: list[SweepTiming | None]  # native scans' own sweep timing (this tree's class)
    resolution: float
    truth: np.ndarray | None  # [N, 3] world poses
    kept: np.ndarray  # [N-1] bool: pairs one scan apart


@dataclass
class Tally:
    cpu_ms: list[float] = field(default_factory=list)
    first_pair_ms: list[float] = field(default_factory=list)
    translation_m: list[float] = field(default_factory=list)
    yaw_deg: list[float] = field(default_factory=list)


def load_drive(folder: Path) -> Drive:
    listing = list_frames(folder)
    views, timings = [], []
    for index in range(len(listing.numbers)):
        scan, timing = scan_and_timing(listing, index)
        views.append(model_crop(scan, min(ODOMETRY_VIEW_SIZE, scan.shape[0])))
        timings.append(timing)
    sequence = read_sequence(folder, estimate_poses=False)
    truth = sequence.poses if sequence.pose_source == "file" else None
    return Drive(
        views, listing.timestamps, timings, listing.resolution, truth, consecutive_pairs(listing.timestamp_texts)
    )


def run(module: ModuleType, drive: Drive, tally: Tally, errors: bool) -> None:
    """One stream over the drive with `module`'s odometry, tallied (its errors too when `errors`: they are the same
    every round)."""
    stream = module.OdometryStream(drive.resolution)
    first_pair = 1
    for k, view in enumerate(drive.views):
        if k and not drive.kept[k - 1]:  # a recording gap: the service restarts the stream's chain (and odometry)
            stream, first_pair = module.OdometryStream(drive.resolution), k + 1
        sweep, timing = drive.timings[k], None
        if sweep is not None:  # as the module's own class: the baseline is another module
            timing = module.SweepTiming(sweep.period_s, sweep.reference_fraction, sweep.azimuths, sweep.seconds)
        start = time.thread_time()
        relative = stream.add(view, drive.stamps[k], timing)
        cost = 1e3 * (time.thread_time() - start)
        tally.cpu_ms.append(cost)
        if k == first_pair:
            tally.first_pair_ms.append(cost)
        if errors and relative is not None and drive.truth is not None:
            error = relative - relative_pose(drive.truth[k], drive.truth[k - 1])
            tally.translation_m.append(float(np.hypot(error[0], error[1])))
            tally.yaw_deg.append(abs(float(np.degrees(wrap_angle(error[2])))))


def pool(tallies: list[Tally]) -> Tally:
    pooled = Tally()
    for tally in tallies:
        for name in ("cpu_ms", "first_pair_ms", "translation_m", "yaw_deg"):
            getattr(pooled, name).extend(getattr(tally, name))
    return pooled


def load_baseline(path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location("odometry_baseline", path)
    if spec is None or spec.loader is None:
        raise ValueError(f"{path} is not a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their module's names through sys.modules
    spec.loader.exec_module(module)
    return module


def cpu_line(name: str, tally: Tally) -> str:
    return (
        f"{name:<9} CPU per frame median {statistics.median(tally.cpu_ms):6.2f} ms, mean "
        f"{statistics.fmean(tally.cpu_ms):6.2f} ms, first pair {statistics.median(tally.first_pair_ms):6.1f} ms"
    )


def error_line(name: str, where: str, tally: Tally) -> str:
    t, y = np.array(tally.translation_m), np.array(tally.yaw_deg)
    if not len(t):
        return f"{name:<9} {where}: no true poses"
    return (
        f"{name:<9} {where}: {len(t)} pairs, translation mean {t.mean():.4f} max {t.max():.3f} m, "
        f"yaw mean {y.mean():.4f} max {y.max():.3f} deg"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.odometry_cost", description=__doc__.splitlines()[0])
    parser.add_argument("sequences", nargs="+", type=Path, help="sequence folders")
    parser.add_argument("--baseline", type=Path, help="a copy of rafd/odometry/registration.py to compare with")
    flags.add_count(parser, "--rounds", 2, 100, "CPU rounds (accuracy is read in the first)")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    for folder in args.sequences:
        if not folder.is_dir():
            parser.error(f"{folder} is not a folder")
    ways = {"this tree": this_odometry}
    if args.baseline is not None:
        if not args.baseline.is_file():
            parser.error(f"--baseline {args.baseline}: no such file")
        ways["baseline"] = load_baseline(args.baseline)
    cv2.setNumThreads(1)  # as the service runs it
    drives = [load_drive(folder) for folder in args.sequences]
    for drive, folder in zip(drives, args.sequences):
        if len(drive.views) < 3:
            parser.error(f"{folder}: {len(drive.views)} frames; needs 3 or more")
    # (way, drive) -> its tally; the CPU figures pool every drive, the errors are printed per drive and pooled
    tallies = {(name, index): Tally() for name in ways for index in range(len(drives))}
    for round_index in progress.track(range(args.rounds), desc="odometry rounds", unit="round"):
        order = list(ways.items()) if round_index % 2 == 0 else list(reversed(ways.items()))
        for index, drive in enumerate(drives):
            for name, module in order:
                run(module, drive, tallies[name, index], errors=round_index == 0)
    frames = sum(len(drive.views) for drive in drives)
    print(f"{len(drives)} sequences, {frames} frames x {args.rounds} rounds, opencv 1 thread")
    pooled = {name: pool([tallies[name, index] for index in range(len(drives))]) for name in ways}
    for index, folder in enumerate(args.sequences):
        for name in ways:
            print(error_line(name, str(folder), tallies[name, index]))
    for name in ways:
        if len(drives) > 1:
            print(error_line(name, "all", pooled[name]))
        print(cpu_line(name, pooled[name]))
    if args.baseline is not None:
        this, base = pooled["this tree"], pooled["baseline"]
        median = statistics.median(this.cpu_ms) / statistics.median(base.cpu_ms)
        mean = statistics.fmean(this.cpu_ms) / statistics.fmean(base.cpu_ms)
        print(f"CPU ratio this tree / baseline: median {median:.2f}, mean {mean:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
