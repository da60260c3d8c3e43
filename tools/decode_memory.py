"""What the largest accepted posted image costs the service's one decode: time and peak memory of
`service.body.images.decode_frame` on the largest native scan the default settings accept (400 azimuths x 6848 range
bins), an Oxford-size native scan, a RADIATE polar scan and a 1152 px Cartesian scan.

    python -m tools.decode_memory [--repeats 5]

Each case runs in a fresh process (so its peak resident memory is its own): the decode is run once to warm up, then
--repeats times; printed are the PNG and inflated sizes, the median and max wall time, and the rise of the process's
peak RSS over what it held before the first decode (ru_maxrss; the arrays of the decode and the conversion). The
scans are speckle (random returns at the real scans' grey levels), so the PNGs are as large as real ones; a zero scan
inflates to the same bytes. Torch-free; runs on loopback nothing.
"""

from __future__ import annotations

import argparse
import base64
import json
import resource
import statistics
import subprocess
import sys
import time

import numpy as np

from rafd import progress
from rafd.cli import flags

CASES = ("native-max", "native-oxford", "polar", "cartesian")


def _image(case: str) -> np.ndarray:
    from rafd.scans.native import SENSOR_SHAPE

    rng = np.random.default_rng(0)
    if case == "cartesian":
        return rng.integers(0, 40, (1152, 1152), dtype=np.uint8)
    if case == "polar":
        return rng.integers(0, 40, (576, 400), dtype=np.uint8)
    bins = SENSOR_SHAPE.max_range_bins if case == "native-max" else 3768
    rows = SENSOR_SHAPE.max_azimuths
    image = rng.integers(0, 40, (rows, 11 + bins), dtype=np.uint8)
    times = 1_547_131_046_353_776 + np.round(np.arange(rows) * 625.0).astype(np.int64)
    encoder = 13 + 14 * np.arange(rows)
    image[:, :8] = times.astype("<i8").view(np.uint8).reshape(rows, 8)
    image[:, 8:10] = encoder.astype("<u2").view(np.uint8).reshape(rows, 2)
    image[:, 10] = 255
    return image


def _child(case: str, repeats: int) -> dict[str, float]:
    import cv2

    from service.body.images import decode_frame

    image = _image(case)
    ok, encoded = cv2.imencode(".png", image)
    assert ok
    text = base64.b64encode(encoded.tobytes()).decode("ascii")
    before_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    decode_frame(text, 256, 0.173611)  # warm-up (the shipped model's input size and resolution)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        decode_frame(text, 256, 0.173611)
        times.append(time.perf_counter() - start)
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "width": image.shape[1],
        "height": image.shape[0],
        "png_mb": len(encoded) / 1e6,
        "inflated_mb": image.shape[0] * (1 + image.shape[1]) / 1e6,
        "median_ms": 1000 * statistics.median(times),
        "max_ms": 1000 * max(times),
        "peak_rise_mb": (peak_kb - before_kb) / 1024,
    }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.decode_memory", description=__doc__.splitlines()[0])
    flags.add_count(parser, "--repeats", 5, 50, "timed decodes per case")
    parser.add_argument("--child", choices=CASES, help=argparse.SUPPRESS)
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    if args.child:
        print(json.dumps(_child(args.child, args.repeats)))
        return 0
    print(f"{'case':<14} {'size':>10} {'PNG MB':>7} {'inflated MB':>11} {'median ms':>9} {'max ms':>7} {'peak +MB':>8}")
    for case in progress.track(CASES, desc="decode cases", unit="case"):
        out = subprocess.run(
            [sys.executable, "-m", "tools.decode_memory", "--child", case, "--repeats", str(args.repeats)],
            check=True,
            capture_output=True,
            text=True,
            timeout=600,
        ).stdout
        row = json.loads(out.strip().splitlines()[-1])
        size = f"{row['width']}x{row['height']}"
        print(
            f"{case:<14} {size:>10} {row['png_mb']:>7.2f} {row['inflated_mb']:>11.2f} {row['median_ms']:>9.1f} "
            f"{row['max_ms']:>7.1f} {row['peak_rise_mb']:>8.1f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
