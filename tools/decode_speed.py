"""What decoding a posted scan costs the service, per posted form, side by side: a full Cartesian scan, RADIATE's
polar scan, a native (Oxford / Boreas) scan and a model-size crop, each as the JSON body carries it (base64 text).

    python -m tools.decode_speed --cartesian DIR [--polar DIR] [--native DIR] [--repeats 15]

Each DIR holds PNG scans of that form (e.g. tiny_foggy/Navtech_Cartesian, tiny_foggy_polar/Navtech_Polar,
oxford_radar_sample/radar); the crops are the Cartesian scans' model-size centres. Times
service.body.images.decode_frame (the hardened PNG path, conversion to the Cartesian grid included) for the shipped
model's input size; rounds interleave the forms; prints each form's median ms and PNG size. Torch-free.
"""

from __future__ import annotations

import argparse
import base64
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from rafd import progress
from rafd.cli import flags
from rafd.config import RaFDConfig
from rafd.preprocess import model_crop
from service.body.images import decode_frame


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.decode_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--cartesian", type=Path, required=True, help="folder of full Cartesian PNG scans")
    parser.add_argument("--polar", type=Path, help="folder of RADIATE Navtech_Polar PNG scans")
    parser.add_argument("--native", type=Path, help="folder of Oxford / Boreas native PNG scans")
    flags.add_count(parser, "--repeats", 15, 1000, "timed decodes per form")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    config = RaFDConfig()
    size, resolution = config.input_size, config.resolution
    cv2.setNumThreads(1)  # as the service runs it
    forms: dict[str, list[bytes]] = {}
    folders = {"full Cartesian scan": args.cartesian, "polar scan": args.polar, "native scan": args.native}
    for name, folder in folders.items():
        if folder is None:
            continue
        files = sorted(folder.glob("*.png"))[:6]
        if not files:
            parser.error(f"{folder}: no PNG files")
        forms[name] = [path.read_bytes() for path in files]
    crops = []
    for data in forms["full Cartesian scan"]:
        scan = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        if scan is None:
            parser.error(f"{args.cartesian}: a file is not a PNG opencv reads")
        crops.append(model_crop(scan, size))
    forms[f"{size} px crop"] = [cv2.imencode(".png", crop)[1].tobytes() for crop in crops]
    bodies = {name: [base64.b64encode(data).decode("ascii") for data in files] for name, files in forms.items()}
    times: dict[str, list[float]] = {name: [] for name in bodies}
    for texts in bodies.values():  # warm-up (conversion maps are built once per process)
        decode_frame(texts[0], size, resolution)
    for repeat in progress.track(range(args.repeats), desc="decode rounds", unit="round"):
        for name, texts in bodies.items():
            text = texts[repeat % len(texts)]
            start = time.perf_counter()
            decode_frame(text, size, resolution)
            times[name].append(1000.0 * (time.perf_counter() - start))
    print(f"decode_frame for a {size} px model, median of {args.repeats} (opencv 1 thread)")
    for name, values in times.items():
        kilobytes = statistics.median(len(data) for data in forms[name]) / 1024
        print(f"{name:<22} {statistics.median(values):7.2f} ms   ({kilobytes:.0f} KiB PNG)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
