"""Hostile load on loopback: a padded-PNG flood beside a normal stream, without and with the flood.

    python -m tools.attack_load [--sample DIR] [--frames 60] [--rate-hz 4] [--flood-connections 8]

Starts `rafd-serve` (the shipped model, or --model) on 127.0.0.1 in a subprocess, then runs a normal stream
under two conditions: full 1152 px RADIATE scans without poses (so decode + odometry + model), multipart like
the README's curl, at the radar's 4 Hz, each answer awaited; meanwhile a probe on its own process asks
/health/ready every 50 ms.
"alone" has nothing else; "under flood" runs beside --flood-connections clients on their own process posting,
back to back, a valid scan padded with zTXt chunks to --flood-bytes (default 2.4 MB, just under the service's body
limit: a larger file gets 413 from its Content-Length at once).
The conditions alternate in --rounds blocks (a shared machine's background load drifts; both see the same).
Prints the normal stream's p50/p99 latency, readiness latency and the flood's answers per status, and exits 1
when the normal stream's p99 under the flood exceeds 2x its unloaded p99, a readiness probe took 100 ms or more
or failed, a normal frame failed, or a flood request was accepted. Bounded: --frames frames per condition, the flood
stops with each flooded block, and --max-seconds caps everything. Loopback only: it serves and attacks 127.0.0.1.
Needs httpx (the dev extra); imports no torch.
"""

from __future__ import annotations

import argparse
import collections
import multiprocessing
import os
import socket
import subprocess
import sys
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench.server import cpu_seconds, free_port, serve_command, wait_ready
from bench.timing import percentile
from rafd import detect_client
from rafd.cpu import usable_cpus
from service.body.png import png_chunk

if TYPE_CHECKING:  # the classes behind multiprocessing.Event() and multiprocessing.Queue()
    import multiprocessing.queues
    import multiprocessing.synchronize

HOST = "127.0.0.1"
READY_PROBE_PERIOD_S = 0.05
READY_LIMIT_S = 0.100
P99_RATIO_LIMIT = 2.0


# ------------------------------------------------------------------------------------------------ inputs
def scans_from(sample: Path | None, count: int = 18) -> list[bytes]:
    """PNG bytes of full scans: the sample's, played forward then backward so the ego motion stays smooth."""
    if sample is not None:
        paths = sorted((Path(sample) / "Navtech_Cartesian").glob("*.png"))[:count]
        if not paths:
            raise SystemExit(f"no Navtech_Cartesian/*.png under {sample}")
        scans = [p.read_bytes() for p in paths]
    else:  # speckle stand-ins of RADIATE's size: the cost per frame is what matters here, not the content
        import cv2

        rng = np.random.default_rng(0)
        scans = [cv2.imencode(".png", rng.integers(0, 40, (1152, 1152), dtype=np.uint8))[1].tobytes() for _ in range(4)]
    return scans + scans[-2:0:-1]


def model_crops(scans: list[bytes], size: int) -> list[bytes]:
    """The low-latency client's frames: each scan's centre crop at the model's input size (rafd.preprocess)."""
    import cv2

    from rafd.preprocess import model_crop

    crops = []
    for scan in scans:
        image = cv2.imdecode(np.frombuffer(scan, np.uint8), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError("a scan is not a decodable PNG")
        crops.append(cv2.imencode(".png", model_crop(image, size))[1].tobytes())
    return crops


def padded_png(scan: bytes, target_bytes: int = 7_700_000) -> bytes:
    """A valid scan with zTXt chunks (each inflating to 8 MB of text) right after IHDR."""
    text = png_chunk(b"zTXt", b"comment\x00\x00" + zlib.compress(b"A" * 8_000_000, 9))
    return scan[:33] + text * max(1, (target_bytes - len(scan)) // len(text)) + scan[33:]


def multipart_request(png: bytes, stream_id: str, timestamp: float) -> bytes:
    """A whole POST /detect request (multipart, like curl -F), ready to send on a raw socket."""
    body = detect_client.multipart_body(detect_client.FrameFields(timestamp, stream_id), png)
    head = (
        f"POST /detect HTTP/1.1\r\nHost: {HOST}\r\nConnection: close\r\n"
        f"Content-Type: {body.content_type}\r\nContent-Length: {len(body.content)}\r\n\r\n"
    )
    return head.encode() + body.content


# ------------------------------------------------------------------------------------------------ the flood
def _flood_connection(
    port: int, request: bytes, stop: threading.Event, counts: collections.Counter, lock: threading.Lock
) -> None:
    while not stop.is_set():
        outcome = "error"
        try:
            with socket.create_connection((HOST, port), timeout=30) as sock:
                try:
                    sock.sendall(request)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # refused before the whole body was read: the answer is still there to read
                data = b""
                while b"\r\n" not in data:
                    chunk = sock.recv(4096)
                    if not chunk:
                        break
                    data += chunk
                if data.startswith(b"HTTP/1.1 "):
                    outcome = data.split(b" ", 2)[1].decode()
        except OSError:
            pass
        with lock:
            counts[outcome] += 1


def flood(
    port: int,
    request: bytes,
    connections: int,
    stop: multiprocessing.synchronize.Event,
    results: multiprocessing.queues.Queue[dict[str, int]],
) -> None:
    """Runs in its own process: `connections` clients posting `request` back to back until `stop`."""
    counts: collections.Counter = collections.Counter()
    lock, local_stop = threading.Lock(), threading.Event()
    threads = [
        threading.Thread(target=_flood_connection, args=(port, request, local_stop, counts, lock), daemon=True)
        for _ in range(connections)
    ]
    for thread in threads:
        thread.start()
    stop.wait()
    local_stop.set()
    for thread in threads:
        thread.join(timeout=60)
    results.put(dict(counts))


# ------------------------------------------------------------------------------------------------ measuring
@dataclass
class Run:
    name: str
    latencies_s: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    ready_s: list[float] = field(default_factory=list)
    ready_failures: int = 0
    flood: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    server_cpu_s: float = 0.0
    flood_cpu_s: float = 0.0
    flood_seconds: float = 0.0  # the flood runs from 1 s before each measured block to its end


def probe_readiness(
    url: str, stop: multiprocessing.synchronize.Event, results: multiprocessing.queues.Queue[list[tuple[float, bool]]]
) -> None:
    """Runs in its own process (so the normal stream's client does not delay it): [(seconds, ok), ...]."""
    import httpx

    probes = []
    with httpx.Client(base_url=url, timeout=10.0) as http:
        while not stop.is_set():
            start = time.perf_counter()
            try:
                ok = http.get("/health/ready").status_code == 200
            except httpx.HTTPError:
                ok = False
            probes.append((time.perf_counter() - start, ok))
            stop.wait(READY_PROBE_PERIOD_S)
    results.put(probes)


def normal_stream(
    url: str, stream_id: str, scans: list[bytes], frames: int, period_s: float, run: Run, with_pose: bool
) -> None:
    """Frames at the sensor's rate, each answer awaited (a radar client does not pipeline its frames); the stream
    goes on from the run's previous block. `with_pose`: send a (stationary) pose, so no odometry runs."""
    import httpx

    with httpx.Client(base_url=url, timeout=60.0) as http:
        next_at = time.perf_counter()
        for _ in range(frames):
            k = len(run.latencies_s)
            start = time.perf_counter()
            fields = detect_client.FrameFields(k + 1, stream_id, (0.0, 0.0, 0.0) if with_pose else None)
            body = detect_client.multipart_body(fields, scans[k % len(scans)])
            response = http.post(
                detect_client.detect_path(flow=False), content=body.content, headers={"content-type": body.content_type}
            )
            run.latencies_s.append(time.perf_counter() - start)
            if response.status_code != 200:
                run.failures.append(f"frame {k + 1}: {response.status_code} {response.text[:200]}")
            next_at += period_s
            time.sleep(max(0.0, next_at - time.perf_counter()))


def measure(
    run: Run,
    url: str,
    scans: list[bytes],
    frames: int,
    period_s: float,
    server_pid: int,
    flood_pid: int | None = None,
    with_pose: bool = False,
) -> None:
    """One block of the normal stream with the readiness probe, added to `run`."""
    stop = multiprocessing.Event()
    results: multiprocessing.queues.Queue[list[tuple[float, bool]]] = multiprocessing.Queue()  # the probes
    prober = multiprocessing.Process(target=probe_readiness, args=(url, stop, results))
    start, server_cpu = time.perf_counter(), cpu_seconds(server_pid)
    flood_cpu = cpu_seconds(flood_pid) if flood_pid else 0.0
    prober.start()
    try:
        normal_stream(url, "normal-" + run.name.replace(" ", "-"), scans, frames, period_s, run, with_pose)
    finally:
        stop.set()
        probes = results.get(timeout=60)
        prober.join(timeout=30)
    run.ready_s += [seconds for seconds, _ in probes]
    run.ready_failures += sum(not ok for _, ok in probes)
    run.seconds += time.perf_counter() - start
    run.server_cpu_s += cpu_seconds(server_pid) - server_cpu
    run.flood_cpu_s += cpu_seconds(flood_pid) - flood_cpu if flood_pid else 0.0


def flood_cost(port: int, request: bytes, connections: int, seconds: float, server_pid: int) -> None:
    """The flood alone: the server's CPU time per flood request (a figure the background load hardly moves)."""
    stop = multiprocessing.Event()
    results: multiprocessing.queues.Queue[dict[str, int]] = multiprocessing.Queue()  # the flood's counts
    flooder = multiprocessing.Process(target=flood, args=(port, request, connections, stop, results))
    cpu = cpu_seconds(server_pid)
    flooder.start()
    time.sleep(seconds)
    stop.set()
    counts = results.get(timeout=120)
    flooder.join(timeout=30)
    used, answered = cpu_seconds(server_pid) - cpu, sum(counts.values())
    print(
        f"flood alone for {seconds:.0f} s: {answered} answers {dict(counts)}, server CPU "
        f"{1000 * used / max(1, answered):.2f} ms per flood request"
    )


def flooded_block(
    run: Run,
    port: int,
    request: bytes,
    connections: int,
    url: str,
    scans: list[bytes],
    frames: int,
    period_s: float,
    server_pid: int,
    with_pose: bool,
) -> None:
    """One block of the normal stream while the flood runs (from 1 s before it); the flood's answers add to `run`."""
    stop = multiprocessing.Event()
    results: multiprocessing.queues.Queue[dict[str, int]] = multiprocessing.Queue()  # the flood's counts
    flooder = multiprocessing.Process(target=flood, args=(port, request, connections, stop, results))
    started = time.perf_counter()
    flooder.start()
    try:
        time.sleep(1.0)  # the flood is under way before the first measured frame
        measure(run, url, scans, frames, period_s, server_pid, flooder.pid, with_pose)
    finally:
        stop.set()
        counts = results.get(timeout=120)
        flooder.join(timeout=30)
        run.flood_seconds += time.perf_counter() - started
    for status, count in counts.items():
        run.flood[status] = run.flood.get(status, 0) + count


# ------------------------------------------------------------------------------------------------ report
def report(alone: Run, flooded: Run) -> list[str]:
    """Prints the figures; returns the criteria that failed."""
    print(
        f"{'run':<12} {'frames':>6} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} | {'ready p50':>9} {'ready p99':>9} "
        f"{'ready max':>9} {'probes':>6} | {'server CPU':>10} {'flood CPU':>9} | flood answers"
    )
    for run in (alone, flooded):
        ms = [1000 * v for v in run.latencies_s]
        ready = [1000 * v for v in run.ready_s]
        flood_text = ", ".join(f"{k}: {v}" for k, v in sorted(run.flood.items())) or "-"
        rate = sum(run.flood.values()) / run.flood_seconds if run.flood else 0.0
        print(
            f"{run.name:<12} {len(ms):>6} {percentile(ms, 50):>7.1f} {percentile(ms, 99):>7.1f} {max(ms):>7.1f} | "
            f"{percentile(ready, 50):>9.1f} {percentile(ready, 99):>9.1f} {max(ready):>9.1f} {len(ready):>6} | "
            f"{100 * run.server_cpu_s / run.seconds:>9.0f}% {100 * run.flood_cpu_s / run.seconds:>8.0f}% | "
            f"{flood_text}" + (f" ({rate:.0f}/s)" if run.flood else "")
        )
    ratio = percentile(flooded.latencies_s, 99) / percentile(alone.latencies_s, 99)
    print(f"normal stream p99 with / without the flood: {ratio:.2f}x (limit {P99_RATIO_LIMIT}x)")
    failed = []
    if ratio > P99_RATIO_LIMIT:
        failed.append(f"p99 ratio {ratio:.2f} > {P99_RATIO_LIMIT}")
    for run in (alone, flooded):
        if run.failures:
            failed.append(f"{run.name}: {len(run.failures)} normal frames failed, e.g. {run.failures[0]}")
        if run.ready_failures or max(run.ready_s, default=0.0) >= READY_LIMIT_S:
            failed.append(f"{run.name}: readiness max {1000 * max(run.ready_s):.1f} ms, {run.ready_failures} failed")
    if flooded.flood.get("200"):
        failed.append(f"{flooded.flood['200']} flood requests were accepted")
    if sum(flooded.flood.values()) == 0:
        failed.append("the flood sent nothing")
    return failed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.attack_load", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sample",
        type=Path,
        default=os.environ.get("RAFD_RADIATE_SAMPLE") or None,
        help="RADIATE sequence for the normal stream (default: $RAFD_RADIATE_SAMPLE, else speckle)",
    )
    parser.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped one)")
    parser.add_argument("--threads", type=int, default=None, help="server onnxruntime threads (default: its CPUs)")
    parser.add_argument(
        "--stream",
        choices=("scans", "crops"),
        default="scans",
        help="normal stream: full 1152 px scans without poses (decode + odometry + model), or the "
        "low-latency client's model-size crops with poses (decode + model)",
    )
    parser.add_argument("--frames", type=int, default=60, help="normal-stream frames per condition")
    parser.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="alternate alone / under-flood blocks this many times (background load drifts)",
    )
    parser.add_argument("--rate-hz", type=float, default=4.0, help="normal-stream frame rate (RADIATE: 4 Hz)")
    parser.add_argument("--flood-connections", type=int, default=8, help="flood clients posting back to back")
    parser.add_argument(
        "--flood-bytes",
        type=int,
        default=2_400_000,
        help="size of the padded PNG (default: just under RAFD_MAX_REQUEST_BYTES, so its chunks are what is refused)",
    )
    parser.add_argument(
        "--flood-cost-seconds",
        type=float,
        default=5.0,
        help="first flood alone this long and print the server's CPU per flood request (0: skip)",
    )
    parser.add_argument("--max-seconds", type=float, default=300.0, help="hard limit on the whole run")
    args = parser.parse_args(argv)
    if (
        not 1 <= args.rounds <= args.frames <= 2000
        or not 0 < args.rate_hz <= 50
        or not 1 <= args.flood_connections <= 256
    ):
        parser.error(
            "bounded load only: 1 <= --rounds <= --frames <= 2000, --rate-hz up to 50, --flood-connections 1-256"
        )

    scans = scans_from(args.sample)
    request = multipart_request(padded_png(scans[0], args.flood_bytes), "flood", 1.0)
    port = free_port()
    url = f"http://{HOST}:{port}"
    # defaults: no keys, default limits (none of this shell's RAFD_* settings)
    server = subprocess.Popen(
        serve_command(port, model=args.model, threads=args.threads),
        env={k: v for k, v in os.environ.items() if not k.startswith("RAFD_")},
    )

    def give_up() -> None:
        server.kill()
        os._exit(2)

    watchdog = threading.Timer(args.max_seconds, give_up)
    watchdog.daemon = True
    watchdog.start()
    try:
        wait_ready(url, server)
        kind = "model-size crops with poses" if args.stream == "crops" else "full scans without poses"
        print(
            f"rafd-serve on {url}; normal stream: {args.frames} {kind} at {args.rate_hz} Hz"
            f" ({'RADIATE sample' if args.sample else 'speckle stand-ins'}); flood: {args.flood_connections} "
            f"connections posting a {len(request) / 1e6:.1f} MB padded PNG; {usable_cpus()} usable CPUs"
        )
        period, with_pose = 1.0 / args.rate_hz, args.stream == "crops"
        if with_pose:
            import httpx

            scans = model_crops(scans, int(httpx.get(f"{url}/model").json()["input_size"]))
        if args.flood_cost_seconds > 0:
            flood_cost(port, request, args.flood_connections, min(args.flood_cost_seconds, 60.0), server.pid)
        measure(Run("warm-up"), url, scans, min(8, args.frames), period, server.pid, None, with_pose)  # first calls
        alone, flooded = Run("alone"), Run("under flood")
        for block in range(args.rounds):
            frames = args.frames // args.rounds + (block < args.frames % args.rounds)
            measure(alone, url, scans, frames, period, server.pid, None, with_pose)
            flooded_block(
                flooded, port, request, args.flood_connections, url, scans, frames, period, server.pid, with_pose
            )
        failed = report(alone, flooded)
    finally:
        watchdog.cancel()
        server.terminate()
        server.wait(timeout=30)
    for reason in failed:
        print(f"FAILED: {reason}")
    print("PASSED" if not failed else "")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
