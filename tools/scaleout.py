"""`python -m tools.scaleout SAMPLE [--replicas 1 3] [--streams 6] [--stream-frames 8]`: frames per second through
nginx (the shipped nginx.conf, on loopback) in front of 1 and of 3 rafd-serve replicas, measured side by side.

The same load for each: `--streams` clients at once, each posting `--frames` real scans of SAMPLE (a RADIATE
folder, full 1152 px PNGs, no poses: the service's odometry runs, as for rafd-client) one after the other to its
own stream, naming it in X-Stream-Id. Each replica runs with its defaults (threads = the CPUs it sees): on one
machine the replicas share its cores, so more replicas add no compute; this measures what routing and the
extra processes cost. Scale-out pays where each replica has its own cores (other machines, or `cpus:` quotas
that add up to no more than the machine). Standard library only (plus the service to run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.loopback import LoopbackCluster
from rafd import progress
from rafd.cli import flags
from rafd.detect_client import FrameFields, base64_png, detect_request, json_body, post


def run_load(url: str, scans: list[Path], streams: int, frames: int) -> tuple[float, list[float], dict[str, int]]:
    """(wall seconds, per-request latencies in seconds, {replica: frames answered})."""
    # The stream named only in X-Stream-Id (the header nginx hashes on), as a client that routes on it may.
    requests = [
        [
            detect_request(
                json_body(FrameFields(1000.0 + t), base64_png(scans[(k * frames + t) % len(scans)].read_bytes())),
                header_stream_id=f"bench-{k}",
            )
            for t in range(frames)
        ]
        for k in range(streams)
    ]
    latencies: list[float] = []
    replicas: dict[str, int] = {}
    errors: list[str] = []
    lock = threading.Lock()

    def client(k: int) -> None:
        for request in requests[k]:
            start = time.perf_counter()
            try:
                with post(url, request, timeout=120) as response:
                    response.read()
                    replica = response.headers["X-RaFD-Replica"].split(", ")[-1]  # the one that answered
            except OSError as exc:
                with lock:
                    errors.append(f"stream {k}: {exc}")
                return
            with lock:
                latencies.append(time.perf_counter() - start)
                replicas[replica] = replicas.get(replica, 0) + 1

    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=streams) as pool:
        list(pool.map(client, range(streams)))  # list(): a client's exception surfaces here
    wall = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"{len(errors)} requests failed, e.g. {errors[0]}")
    return wall, latencies, replicas


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.scaleout", description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path, help="RADIATE folder with Navtech_Cartesian/*.png (e.g. tiny_foggy)")
    parser.add_argument(
        "--replicas", type=int, nargs="+", default=[1, 3], help="cluster sizes to measure (default 1 3)"
    )
    parser.add_argument("--streams", type=int, default=6, help="concurrent clients, one stream each")
    parser.add_argument("--stream-frames", type=int, default=8, help="frames each stream posts (default %(default)s)")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    scans = sorted((args.sample / "Navtech_Cartesian").glob("*.png"))
    if not scans:
        print(f"bench: no Navtech_Cartesian/*.png in {args.sample}", file=sys.stderr)
        return 2
    rows = []
    for replicas in progress.track(args.replicas, desc="cluster sizes", unit="cluster"):
        with tempfile.TemporaryDirectory(prefix="rafd-scaleout-") as work:
            try:
                with LoopbackCluster(replicas, Path(work)) as cluster:
                    wall, latencies, spread = run_load(cluster.url, scans, args.streams, args.stream_frames)
            except RuntimeError as exc:
                print(f"bench: {exc}", file=sys.stderr)
                return 1
        frames = args.streams * args.stream_frames
        rows.append(
            (
                replicas,
                frames,
                wall,
                frames / wall,
                statistics.median(latencies) * 1e3,
                sorted(spread.values(), reverse=True),
            )
        )
    print(f"{args.streams} streams x {args.stream_frames} frames (1152 px scans, odometry), through nginx")
    print(f"{'replicas':>8} {'frames':>6} {'wall s':>7} {'frames/s':>8} {'median ms':>9}  frames per replica")
    for replicas, frames, wall, fps, median, per_replica in rows:
        print(f"{replicas:>8} {frames:>6} {wall:>7.2f} {fps:>8.2f} {median:>9.1f}  {per_replica}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
