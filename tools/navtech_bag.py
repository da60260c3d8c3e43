"""Native radar scans (Oxford / Boreas PNGs) -> a ROS 2 bag as Navtech's ROS 2 driver records them: one
navtech_msgs/RadarBScanMsg per scan on /radar_data/b_scan_msg and a RadarConfigurationMsg on
/radar_data/configuration_data, for checking `rafd client BAG` on real scans without committing a bag.

    python -m tools.navtech_bag OUT_BAG SCAN.png [SCAN.png ...] [--range-bin-m 0.0432] [--storage sqlite3]

What the driver writes (its b_scan_extended_publisher): the image one row per azimuth, 8UC1; `encoder_values` and
`timestamps` (UNIX ns) per row; the image's header stamp is the time of azimuth 199, frame "b_scan_extended"; the
message is logged once the rotation is complete. Its configuration carries the bin size in the radar's unit (tenths
of a millimetre), typed fields as in the FoMo dataset's bags or, with layout="legacy", the older drivers' big-endian
byte arrays. A native PNG's valid flag (column 10) has no place in the message: the driver knows none.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from rafd.ros import types
from rafd.ros.answers import header
from rafd.ros.build import make
from rafd.ros.writer import BagWriter
from rafd.scans.native import HEADER_COLUMNS, native_format_name, parse_native_scan

SCAN_TOPIC = "/radar_data/b_scan_msg"
CONFIGURATION_TOPIC = "/radar_data/configuration_data"
STAMP_ROW = 199  # the driver stamps a rotation with its azimuth 199's time
FRAME_ID = "b_scan_extended"


def _store(layout: str):
    """The writer's types: the configuration in the typed layout, or the older drivers' under its real name."""
    if layout == "typed":
        return types.typestore()
    from rosbags.typesys import get_types_from_msg

    legacy = types.shipped_definitions()[types.LEGACY_CONFIGURATION]
    return types.typestore(dict(get_types_from_msg(legacy, types.CONFIGURATION)))


def _configuration(store, stamp_ns: int, azimuths: int, bins: int, range_bin_m: float, layout: str):
    tenths_mm = range_bin_m * 10_000.0  # the radar's unit
    if layout == "typed":
        return make(
            store,
            types.CONFIGURATION,
            header=header(store, stamp_ns, "navtech_config"),
            azimuth_samples=azimuths,
            encoder_size=5600,
            azimuth_offset=0,
            bin_size=tenths_mm,
            range_in_bins=bins,
            expected_rotation_rate=4,
            range_gain=1.0,
            range_offset=0.0,
        )

    def big_endian(value: int, size: int) -> np.ndarray:
        return np.frombuffer(int(value).to_bytes(size, "big"), np.uint8).copy()

    return make(
        store,
        types.CONFIGURATION,
        header=header(store, stamp_ns, "navtech_config"),
        azimuth_samples=big_endian(azimuths, 2),
        encoder_size=big_endian(5600, 2),
        bin_size=big_endian(round(tenths_mm), 8),
        range_in_bins=big_endian(bins, 2),
        expected_rotation_rate=big_endian(4, 2),
        range_gain=big_endian(1, 4),
        range_offset=big_endian(0, 4),
    )


def b_scan_message(store, native: np.ndarray):
    """A native scan (uint8 [A, 11 + R]) -> (RadarBScanMsg as the driver writes it, its log time ns)."""
    times_us = np.ascontiguousarray(native[:, :8]).view("<i8").ravel().astype(np.int64)
    encoder = np.ascontiguousarray(native[:, 8:10]).view("<u2").ravel().astype(np.uint16)
    pixels = np.ascontiguousarray(native[:, HEADER_COLUMNS:])
    azimuths, bins = pixels.shape
    stamp_ns = int(times_us[min(STAMP_ROW, azimuths - 1)]) * 1000
    image = make(
        store,
        types.IMAGE,
        header=header(store, stamp_ns, FRAME_ID),
        height=azimuths,
        width=bins,
        encoding="8UC1",
        is_bigendian=0,
        step=bins,
        data=pixels.reshape(-1),
    )
    message = make(
        store, types.B_SCAN, b_scan_img=image, encoder_values=encoder, timestamps=(times_us * 1000).astype(np.uint64)
    )
    return message, int(times_us[-1]) * 1000 + 1_000_000  # logged 1 ms after the rotation's last azimuth


def write_navtech_bag(
    out: Path,
    scans: Sequence[np.ndarray],
    range_bin_m: float,
    storage: str = "mcap",
    layout: str = "typed",
    with_configuration: bool = True,
) -> Path:
    """`scans` (native uint8 [A, 11 + R] each, in time order) -> a bag at `out` as Navtech's driver records it."""
    store = _store(layout)
    with BagWriter(out, storage, store) as bag:
        for index, native in enumerate(scans):
            message, log_ns = b_scan_message(store, native)
            if index == 0 and with_configuration:
                azimuths, bins = native.shape[0], native.shape[1] - HEADER_COLUMNS
                first_ns = int(np.ascontiguousarray(native[0, :8]).view("<i8")[0]) * 1000
                configuration = _configuration(store, first_ns, azimuths, bins, range_bin_m, layout)
                bag.write(CONFIGURATION_TOPIC, types.CONFIGURATION, first_ns, configuration)
            bag.write(SCAN_TOPIC, types.B_SCAN, log_ns, message)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.navtech_bag", description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the bag to write (a folder; must not exist)")
    parser.add_argument("scans", type=Path, nargs="+", help="native scan PNGs, in time order")
    parser.add_argument("--range-bin-m", type=float, help="metres per range bin (default: the scans' dataset's)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--layout", choices=("typed", "legacy"), default="typed", help="the configuration's fields")
    args = parser.parse_args(argv)
    images: list[np.ndarray] = []
    for path in args.scans:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            print(f"navtech_bag: {path} does not read as a PNG", file=sys.stderr)
            return 2
        images.append(image)
    first = images[0]
    range_bin = (
        args.range_bin_m or parse_native_scan(first, native_format_name(first.shape[1], first[:, 10])).fmt.range_bin_m
    )
    write_navtech_bag(args.out, images, range_bin, args.storage, args.layout)
    print(f"wrote {len(images)} scans to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
