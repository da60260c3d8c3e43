"""rafd polar: convert a sequence's polar scans to RADIATE's Cartesian grid; compare with RADIATE's own images.

With --compare CARTESIAN_SEQ: per frame, the mean absolute grey difference and the correlation inside the disc, for
RADIATE's conventions and for bin centres; with --fit as well, a search, frame by frame, of the sample offsets and
the radar's pixel that best reproduce RADIATE's image (how RADIATE_POLAR was set: frame 1's values, rounded). With
--out DIR: the converted scans as DIR/Navtech_Cartesian/NNNNNN.png and their timestamps. A native folder
(Oxford Radar RobotCar, Boreas: radar/<microseconds>.png) converts the same way, with DIR/ego_poses.csv from its
ground-truth odometry when the folder has it.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from rafd.cli import flags
from rafd.data.folders import POLAR_DIR, POLAR_TIMESTAMPS_FILE
from rafd.data.frames import RadarSequence
from rafd.data.native_folder import is_native_folder
from rafd.data.poses import POSES_FILE, write_ego_poses
from rafd.data.radiate_files import read_timestamps
from rafd.data.reader import read_sequence
from rafd.geometry import RADIATE_SCAN_SIZE
from rafd.progress import track
from rafd.ros.sequence import is_bag
from rafd.scans.cartesian import load_image
from rafd.scans.native import NativeSource, read_native_scan
from rafd.scans.native import to_cartesian as native_to_cartesian
from rafd.scans.polar import NOMINAL_POLAR, RADIATE_POLAR, PolarConventions, polar_to_cartesian, scan_agreement

FIT_STEPS = (0.25, 0.25, 0.5, 0.5)  # first step of (azimuth offset, range offset, centre u, centre v)
FIT_HALVINGS = 6  # final step 1/64 of the first: below 0.01 bins / pixels


def fit_conventions(
    polar: np.ndarray, reference: np.ndarray, start: PolarConventions = NOMINAL_POLAR
) -> PolarConventions:
    """The sample offsets and radar pixel that minimise the mean absolute grey difference between the converted
    `polar` and the Cartesian `reference` (coordinate search, halving the step until it stops improving)."""
    size = reference.shape[0]

    def cost(params: np.ndarray) -> float:
        conventions = dataclasses.replace(
            start,
            azimuth_offset=float(params[0]),
            range_offset=float(params[1]),
            centre_offset=(float(params[2]), float(params[3])),
        )
        return scan_agreement(polar_to_cartesian(polar, size, conventions=conventions), reference)[0]

    params = np.array([start.azimuth_offset, start.range_offset, *start.centre_offset], dtype=np.float64)
    steps = np.array(FIT_STEPS)
    best = cost(params)
    for _ in range(FIT_HALVINGS + 1):
        improved = True
        while improved:
            improved = False
            for k in range(len(params)):
                for sign in (-1.0, 1.0):
                    trial = params.copy()
                    trial[k] += sign * steps[k]
                    value = cost(trial)
                    if value < best:
                        best, params, improved = value, trial, True
        steps /= 2.0
    rounded = [round(float(p), 3) for p in params]
    return dataclasses.replace(
        start, azimuth_offset=rounded[0], range_offset=rounded[1], centre_offset=(rounded[2], rounded[3])
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("polar"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "sequence",
        type=Path,
        metavar="POLAR_SEQ",
        help=f"folder holding {POLAR_DIR}/ and {POLAR_TIMESTAMPS_FILE}, a native folder (radar/<microseconds>.png) or "
        "a ROS 2 bag",
    )
    parser.add_argument(
        "--compare", type=Path, metavar="CARTESIAN_SEQ", help="RADIATE folder with the same frames' Navtech_Cartesian/"
    )
    parser.add_argument("--fit", action="store_true", help="with --compare: fit the conventions on each frame")
    flags.add_out(parser, "DIR", "write the converted scans as DIR/Navtech_Cartesian/ + Navtech_Cartesian.txt")
    parser.add_argument(
        "--scan-size", type=int, default=None, metavar="PX", help="Cartesian side in pixels (default: the whole disc)"
    )
    parser.add_argument("--repeats", type=int, default=20, help="conversions timed per run (median reported)")
    flags.add_quiet(parser)
    return parser


def _fail(message: str) -> int:
    print(f"rafd-polar: error: {message}", file=sys.stderr)
    return 2


def _print_timing(what: str, convert: Callable[[], object], repeats: int) -> None:
    """Time one scan's conversion `repeats` times (at least once) and print the median."""
    seconds = []
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        convert()
        seconds.append(time.perf_counter() - start)
    print(f"conversion {what}: median {1e3 * float(np.median(seconds)):.2f} ms over {len(seconds)} runs (maps cached)")


def _write_scans(image_dir: Path, scans: dict[int, np.ndarray]) -> int | None:
    """Each scan as image_dir/NNNNNN.png; the exit status of the first failure, else None."""
    image_dir.mkdir(parents=True, exist_ok=True)
    for number, scan in scans.items():
        if not cv2.imwrite(str(image_dir / f"{number:06d}.png"), scan):
            return _fail(f"could not write {image_dir / f'{number:06d}.png'}")
    return None


def _write_sequence_scans(out: Path, scans: dict[int, np.ndarray], sequence: RadarSequence) -> int | None:
    """A converted sequence's scans as out/Navtech_Cartesian/ with their times in out/Navtech_Cartesian.txt, as
    RADIATE lays them out; the exit status of the first failure, else None."""
    failure = _write_scans(out / "Navtech_Cartesian", scans)
    if failure is None:
        (out / "Navtech_Cartesian.txt").write_text(
            "".join(f"Frame: {f.number:06d} Time: {f.timestamp_text}\n" for f in sequence.frames)
        )
    return failure


def convert_native(args: argparse.Namespace) -> int:
    """A native folder (rafd.data.native_folder) -> its scans on RADIATE's grid, timed, optionally written out."""
    if args.compare is not None or args.fit:
        return _fail(
            "--compare and --fit compare RADIATE's polar scans with RADIATE's images; a native folder has none"
        )
    try:
        sequence = read_sequence(args.sequence, estimate_poses=False)
        source = sequence.frames[0].polar
        assert isinstance(source, NativeSource)  # a native folder's frames convert through one
        first = read_native_scan(sequence.frames[0].image_path, source.fmt)
        size = args.scan_size or RADIATE_SCAN_SIZE
        scans = {
            frame.number: native_to_cartesian(read_native_scan(frame.image_path, first.fmt), size)
            for frame in sequence.frames
        }
    except (OSError, ValueError) as error:
        return _fail(str(error))
    _print_timing(
        f"{first.power.shape[0]} azimuths x {first.range_bins} bins ({first.fmt.name}) -> {size} px",
        lambda: native_to_cartesian(first, size),
        args.repeats,
    )
    if args.out is not None:
        image_dir = args.out / "Navtech_Cartesian"
        failure = _write_sequence_scans(args.out, scans, sequence)
        if failure is not None:
            return failure
        if sequence.poses is not None:
            write_ego_poses(
                args.out / POSES_FILE,
                [f.number for f in sequence.frames],
                [f.timestamp_text for f in sequence.frames],
                sequence.poses,
            )
        print(f"wrote {len(scans)} scans to {image_dir}")
    return 0


def convert_bag(args: argparse.Namespace) -> int:
    """A ROS 2 bag's scans (rafd.ros.sequence) -> RADIATE's grid, optionally written out like a native folder's."""
    if args.compare is not None or args.fit:
        return _fail("--compare and --fit compare RADIATE's polar scans with RADIATE's images; a bag has none")
    try:
        sequence = read_sequence(args.sequence, estimate_poses=False)
        size = args.scan_size or RADIATE_SCAN_SIZE
        scans = {frame.number: _resized(frame.load(), size) for frame in sequence.frames}
    except (OSError, ValueError) as error:
        return _fail(str(error))
    print(f"{len(scans)} scans of {args.sequence} converted to {size} px")
    if args.out is not None:
        image_dir = args.out / "Navtech_Cartesian"
        failure = _write_sequence_scans(args.out, scans, sequence)
        if failure is not None:
            return failure
        print(f"wrote {len(scans)} scans to {image_dir}")
    return 0


def _resized(scan: np.ndarray, size: int) -> np.ndarray:
    """A 1152 px scan's centre `size` px (or the scan itself)."""
    if size >= scan.shape[0]:
        return scan
    offset = (scan.shape[0] - size) // 2
    return scan[offset : offset + size, offset : offset + size]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    flags.apply_quiet(args)
    if is_bag(args.sequence):
        return convert_bag(args)
    if is_native_folder(args.sequence):
        return convert_native(args)
    try:
        listed = read_timestamps(args.sequence / POLAR_TIMESTAMPS_FILE)
        polars = {number: load_image(args.sequence / POLAR_DIR / f"{number:06d}.png") for number, _, _ in listed}
        scans = {number: polar_to_cartesian(polar, args.scan_size) for number, polar in polars.items()}
    except (OSError, ValueError) as error:
        return _fail(str(error))
    if args.compare is not None:
        print(f"{'frame':>6} {'conventions':>12} {'MAD grey':>9} {'correlation':>12}")
        for number, polar in polars.items():
            path = args.compare / "Navtech_Cartesian" / f"{number:06d}.png"
            try:
                reference = load_image(path)
            except (OSError, ValueError) as error:
                return _fail(str(error))
            if reference.shape != scans[number].shape:
                return _fail(f"{path} is {reference.shape}, the converted scan {scans[number].shape}: pass --scan-size")
            for name, conventions in (("radiate", RADIATE_POLAR), ("bin centres", NOMINAL_POLAR)):
                mad, correlation = scan_agreement(
                    polar_to_cartesian(polar, args.scan_size, conventions=conventions), reference
                )
                print(f"{number:>6} {name:>12} {mad:>9.3f} {correlation:>12.4f}")
        if args.fit:
            for number, polar in track(polars.items(), desc="fit the conventions", total=len(polars), unit="frame"):
                reference = load_image(args.compare / "Navtech_Cartesian" / f"{number:06d}.png")
                fitted = fit_conventions(polar, reference)
                converted = polar_to_cartesian(polar, args.scan_size, conventions=fitted)
                mad, correlation = scan_agreement(converted, reference)
                print(
                    f"{number:>6} {'fitted':>12} {mad:>9.3f} {correlation:>12.4f}   azimuth_offset "
                    f"{fitted.azimuth_offset} range_offset {fitted.range_offset} "
                    f"centre_offset {fitted.centre_offset}"
                )
    elif args.fit:
        return _fail("--fit needs --compare CARTESIAN_SEQ")
    first = next(iter(polars.values()))
    _print_timing(
        f"{first.shape[0]}x{first.shape[1]} -> {scans[listed[0][0]].shape[0]} px",
        lambda: polar_to_cartesian(first, args.scan_size),
        args.repeats,
    )
    if args.out is not None:
        image_dir = args.out / "Navtech_Cartesian"
        failure = _write_scans(image_dir, scans)
        if failure is not None:
            return failure
        shutil.copyfile(args.sequence / POLAR_TIMESTAMPS_FILE, args.out / "Navtech_Cartesian.txt")
        print(f"wrote {len(scans)} scans to {image_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
