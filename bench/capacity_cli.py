"""`rafd bench capacity`: how many radars at 4 Hz one replica holds (bench.capacity), per model, coverage and input.

For each config (the shipped default model; the paper's network with random weights, exported here) and each
coverage (--ranges: `whole`, the service's default, detects over the whole scan; a number of metres sets
RAFD_DETECT_RANGE_M) a real `rafd-serve` runs on loopback with the given threads; for each form of input (full 1152 px
scans with poses; the same without poses, so the service's odometry runs; model-size crops with poses) the number of
streams rises until the p99 latency leaves the budget or an answer is not 200. Prints the largest N that held, one
stream alone (p50 / p99), and the answers' own time split by stage at both; --json writes every level.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.capacity import STAGES, encode_frames, find_capacity, looped_scans, run_level
from bench.machine import machine_description
from bench.server import start_server
from rafd.cli import flags

INPUTS = ("posed-scans", "scans", "crops")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("bench capacity"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("sample", type=Path, help="a RADIATE sequence of real scans (tiny_foggy)")
    parser.add_argument("--configs", default="default", help="comma list of default, paper")
    parser.add_argument("--model", type=Path, help="serve this ONNX model as the default config instead")
    parser.add_argument(
        "--inputs",
        default="posed-scans,scans,crops",
        help="comma list: posed-scans (full scans with poses), scans (full scans, no poses: odometry runs), crops "
        "(model-size, with poses)",
    )
    parser.add_argument(
        "--ranges",
        default="whole",
        help="comma list of coverages: whole (the whole scan, the default service) or metres (RAFD_DETECT_RANGE_M)",
    )
    parser.add_argument("--multipart", action="store_true", help="post multipart files instead of JSON + base64")
    parser.add_argument("--seconds", type=float, default=10.0, help="seconds per load level")
    parser.add_argument("--budget-ms", type=float, default=250.0, help="p99 latency a level must stay within")
    parser.add_argument("--max-streams", type=int, default=64, help="the largest number of streams to try")
    flags.add_quiet(parser)
    flags.add_threads(parser, None, "the service's (default: its CPUs)")
    parser.add_argument(
        "--env", action="append", default=[], metavar="RAFD_X=V", help="extra service settings for the run (repeatable)"
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write every level as JSON")
    return parser


def _model_for(config: str, work: Path, model: Path | None) -> Path:
    if config == "default":
        if model is not None:
            return model
        from rafd.assets import default_onnx

        return default_onnx()
    from bench.speed import config_checkpoint, export_step

    return export_step(config_checkpoint(work, config), work)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    inputs = [i.strip() for i in args.inputs.split(",") if i.strip()]
    ranges = [r.strip() for r in args.ranges.split(",") if r.strip()]
    bad = [c for c in configs if c not in ("default", "paper")] + [i for i in inputs if i not in INPUTS]
    bad += [r for r in ranges if r != "whole" and not r.replace(".", "", 1).isdigit()]
    if bad:
        print(f"rafd bench capacity: error: unknown configs or inputs {bad}", file=sys.stderr)
        return 2
    env = dict(item.split("=", 1) for item in args.env)
    try:
        scans = looped_scans(args.sample)
    except FileNotFoundError as error:
        print(f"rafd bench capacity: error: {error}", file=sys.stderr)
        return 2
    from rafd.odometry.registration import estimate_sequence_poses

    poses = estimate_sequence_poses(scans, 0.173611)  # what the vehicle's localisation would send
    report: dict[str, Any] = {"machine": machine_description(args.threads or 0), "levels": {}}
    rows = []
    with tempfile.TemporaryDirectory(prefix="rafd-capacity-") as tmp:
        for config, coverage in [(c, r) for c in configs for r in ranges]:
            model = _model_for(config, Path(tmp), args.model)
            served_env = env if coverage == "whole" else {**env, "RAFD_DETECT_RANGE_M": coverage}
            config_label = config if coverage == "whole" else f"{config}, within {coverage} m"
            with start_server(model, args.threads, env=served_env, clean_env=True) as server:
                import urllib.request

                with urllib.request.urlopen(f"{server.url}/model") as response:
                    described = json.loads(response.read())
                size = int(described["input_size"])
                runtime = described["runtime"]  # what the service chose to serve: the figures are that path's
                served = f"{runtime['runtime']}/{runtime['precision']}"
                report.setdefault("served", {})[config_label] = {
                    "runtime": served,
                    "float32_islands": runtime.get("float32_islands", []),
                    "selection_ms_per_run": runtime.get("selection_ms_per_run", {}),
                }
                print(
                    f"{config_label}: served as {served} (ms a run at start-up: {runtime.get('selection_ms_per_run')})"
                )
                for form in inputs:
                    frames = encode_frames(scans, size if form == "crops" else None)
                    with_poses = None if form == "scans" else poses
                    label = f"{config_label}, {frames.label}, {'poses' if with_poses is not None else 'no poses'}"
                    print(f"{label}:")
                    run_level(server.url, frames, 1, 2.0, poses=with_poses, multipart=args.multipart)  # warm up
                    alone = run_level(server.url, frames, 1, args.seconds, poses=with_poses, multipart=args.multipart)
                    held, levels = find_capacity(
                        server.url,
                        frames,
                        args.budget_ms,
                        args.seconds,
                        with_poses,
                        args.multipart,
                        limit=args.max_streams,
                        log=(lambda _: None) if args.quiet else print,
                    )
                    top = next((lv for lv in levels if lv.streams == held), alone)
                    rows.append((label, held, alone, top))
                    report["levels"][label] = {
                        "alone": alone.summary(),
                        "held": held,
                        "levels": [lv.summary() for lv in levels],
                    }
    print(f"\nmachine: {report['machine']}")
    stages = " / ".join(s[:-3] for s in STAGES)
    print(
        f"| config, input | streams held (p99 <= {args.budget_ms:g} ms, all 200) | 1 stream p50 / p99 ms "
        f"| 1 stream: {stages} (p50 ms) | at the held N: p50 / p99 ms |"
    )
    print("|---|---|---|---|---|")
    for label, held, alone, top in rows:
        split = " / ".join(f"{alone.stage(s):.1f}" for s in STAGES)
        print(
            f"| {label} | {held} | {alone.p(50):.0f} / {alone.p(99):.0f} | {split} | "
            f"{top.p(50):.0f} / {top.p(99):.0f} |"
        )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
