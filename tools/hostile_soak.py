"""Soak under hostile load: normal streams at a held load for a bounded time, with each attack of issue 34 in turn.

    python -m tools.hostile_soak [--sample DIR] [--minutes 5] [--block-seconds 15] [--streams 2]
        [--attacks headers,slow-bodies,json-floats,json-keys]      # runnable for hours: --minutes 240

Starts `rafd-serve` (the shipped model, default settings: no RAFD_* of this shell) on 127.0.0.1. For the whole run,
--streams normal streams post full 1152 px RADIATE scans without poses (decode + odometry + model), multipart like
the README's curl, at the radar's --rate-hz, each answer awaited, from 127.0.0.1 (one process); a probe asks
/health/ready every 50 ms (its own process). Blocks of --block-seconds alternate: quiet, then an attack, quiet, the
next attack, ... for as many rounds as fit in --minutes (at least one). Each attack runs in its own process from
127.0.0.2, another client than the normal streams (the service tells clients apart by address):

- headers: 8 connections sending `GET /health/live` with one endless header (issue finding 1: 128 MiB each);
- slow-bodies: 64 connections sending a /detect head with Content-Length 100000, then 1 byte per second
  (finding 2), reconnecting when answered;
- json-floats: 4 connections posting, back to back, JSON bodies of floats just under RAFD_MAX_REQUEST_BYTES
  (finding 3; larger ones get 413 from their Content-Length at once);
- json-keys: 8 connections posting JSON bodies of ~200k keys, just under the limit (finding 3);
- png-flood: 8 connections posting a scan padded with zTXt chunks to just under the limit (tools/attack_load.py);
- wide-native (issue 40, finding 1): 8 connections posting an all-zero native scan 400 x 400,000 (389 KB, 160 MB
  inflated; before, 15 s and +3.3 GB each), multipart;
- degenerate-native (finding 4): 4 connections posting an Oxford-size native scan whose encoder angles are all
  equal (1.1 MB, multipart): it costs an inflate and a decode before its header is refused;
- forwarded (finding 3): 64 slow-body connections, each with a made-up X-Forwarded-For of its own (the attacker
  reaches the replica directly: its address is not a trusted proxy), so they are one client's 16 requests.

A warm-up comes first and is not measured: the normal load alone, then each attack for 5 s. The first second of
every block is left out (the attack starting or stopping). Prints per phase the normal streams' requests and
latency p50 / p99 (and p99 against the quiet blocks'), readiness p50 / p99 / max, the normal streams' answers by
status and the attackers' answers by status; then the server's RSS after the warm-up, at the end and at its
highest. Exits 1 when, for any attack, readiness p99 exceeded 100 ms, the normal p99 exceeded 2x the quiet p99, a
normal request failed, any answer was a 5xx, or RSS grew by more than 10% after warm-up. Loopback only; bounded by
--minutes and a hard watchdog. Needs httpx (the dev extra); imports no torch.
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing
import os
import select
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench.server import free_port, rss_bytes, serve_command, wait_ready
from bench.timing import percentile
from rafd import detect_client
from rafd.cpu import usable_cpus
from service.body.png import PNG_SIGNATURE, png_chunk
from tools.attack_load import multipart_request, padded_png, scans_from

if TYPE_CHECKING:
    import multiprocessing.queues
    import multiprocessing.synchronize

HOST = "127.0.0.1"
ATTACKER = "127.0.0.2"
READY_PROBE_PERIOD_S = 0.05
READY_LIMIT_MS = 100.0
P99_RATIO_LIMIT = 2.0
RSS_GROWTH_LIMIT = 0.10
SETTLE_S = 1.0  # left out at the start of each block
WARM_UP_ATTACK_S = 5.0
BODY_LIMIT = 5 * 512 * 1024  # RAFD_MAX_REQUEST_BYTES's default
ATTACKS = (
    "headers",
    "slow-bodies",
    "json-floats",
    "json-keys",
    "png-flood",
    "wide-native",
    "degenerate-native",
    "forwarded",
)
DEFAULT_ATTACKS = ("headers", "slow-bodies", "json-floats", "json-keys")


# ------------------------------------------------------------------------------------------------ attacks
def _connect(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((ATTACKER, 0))
    sock.settimeout(10.0)
    sock.connect((HOST, port))
    return sock


def _status(sock: socket.socket, timeout: float = 10.0) -> str:
    """The status of the answer on `sock` (reads its first line), or what went wrong."""
    sock.settimeout(timeout)
    data = b""
    try:
        while b"\r\n" not in data:
            chunk = sock.recv(4096)
            if not chunk:
                break
            data += chunk
    except OSError as exc:
        return type(exc).__name__
    return data.split(b" ", 2)[1].decode() if data.startswith(b"HTTP/1.1 ") else "no answer"


def _post(path: str, body: bytes, content_type: str = "application/json") -> bytes:
    head = (
        f"POST {path} HTTP/1.1\r\nHost: {HOST}\r\nConnection: close\r\nContent-Type: {content_type}\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    )
    return head.encode() + body


def float_body() -> bytes:
    numbers = b", ".join([b"1.2345678e-3"] * ((BODY_LIMIT - 4096) // 14))
    return _post("/detect", b'{"stream_id": "floats", "timestamp": 1, "image": "AAAA", "x": [' + numbers + b"]}")


def key_body() -> bytes:
    keys, size, k = [], 0, 0
    while size < BODY_LIMIT - 4096:
        item = f'"key{k}": {k}'
        keys.append(item)
        size += len(item) + 2
        k += 1
    return _post("/detect", ("{" + ", ".join(keys) + "}").encode())


def one_request(port: int, request: bytes) -> str:
    with _connect(port) as sock:
        try:
            sock.sendall(request)
        except (BrokenPipeError, ConnectionResetError):
            pass  # refused before the whole body was read: the answer may still be there
        return _status(sock)


def endless_header(port: int, stop: threading.Event) -> str:
    with _connect(port) as sock:
        try:
            sock.sendall(b"GET /health/live HTTP/1.1\r\nHost: x\r\nX-Big: ")
            chunk, sent = b"a" * 65536, 0
            while sent < 128 << 20 and not stop.is_set():
                sock.sendall(chunk)
                sent += len(chunk)
        except OSError:
            pass
        return _status(sock)


def wide_native_request() -> bytes:
    """The all-zero 400 x 400,000 native scan of issue 40 (389 KB as a PNG), multipart."""
    header = png_chunk(b"IHDR", struct.pack(">IIBBBBB", 400_000, 400, 8, 0, 0, 0, 0))
    deflate = zlib.compressobj(9)
    row = bytes(400_001)
    data = b"".join(deflate.compress(row) for _ in range(400)) + deflate.flush()
    image = PNG_SIGNATURE + header + png_chunk(b"IDAT", data) + png_chunk(b"IEND", b"")
    return multipart_request(image, "wide", 1.0)


def degenerate_native_request() -> bytes:
    """An Oxford-size native scan (speckle returns) whose encoder angles are all equal, multipart."""
    import cv2

    rng = np.random.default_rng(40)
    image = rng.integers(0, 40, (400, 11 + 3768), dtype=np.uint8)
    times = 1_547_131_046_353_776 + np.round(np.arange(400) * 625.0).astype(np.int64)
    image[:, :8] = times.astype("<i8").view(np.uint8).reshape(400, 8)
    image[:, 8:10] = 0  # every encoder angle 0
    image[:, 10] = 255
    return multipart_request(cv2.imencode(".png", image)[1].tobytes(), "degenerate", 1.0)


def slow_body(port: int, stop: threading.Event, forwarded: str | None = None) -> str:
    with _connect(port) as sock:
        extra = f"X-Forwarded-For: {forwarded}\r\n".encode() if forwarded else b""
        sock.sendall(
            b"POST /detect HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            + extra
            + b"Content-Length: 100000\r\n\r\n{"
        )
        while not stop.is_set():
            if select.select([sock], [], [], 1.0)[0]:
                return _status(sock)
            try:
                sock.sendall(b" ")
            except OSError:
                return _status(sock)
        return "stopped"


def attack(
    name: str,
    port: int,
    stop: multiprocessing.synchronize.Event,
    results: multiprocessing.queues.Queue[dict[str, int]],
    sample: Path | None,
) -> None:
    """Runs in its own process: the attack's connections, each in a loop, until `stop`; puts its answers by status."""
    counts: collections.Counter[str] = collections.Counter()
    lock, local_stop = threading.Lock(), threading.Event()
    if name == "png-flood":
        request = multipart_request(padded_png(scans_from(sample)[0], BODY_LIMIT - 200_000), "flood", 1.0)
    elif name == "json-floats":
        request = float_body()
    elif name == "json-keys":
        request = key_body()
    elif name == "wide-native":
        request = wide_native_request()
    elif name == "degenerate-native":
        request = degenerate_native_request()
    connections = {
        "headers": 8,
        "slow-bodies": 64,
        "json-floats": 4,
        "json-keys": 8,
        "png-flood": 8,
        "wide-native": 8,
        "degenerate-native": 4,
        "forwarded": 64,
    }[name]
    made_up = iter(range(1 << 30))  # a new X-Forwarded-For per connection of the forwarded attack

    def loop() -> None:
        while not local_stop.is_set():
            try:
                if name == "headers":
                    outcome = endless_header(port, local_stop)
                elif name == "slow-bodies":
                    outcome = slow_body(port, local_stop)
                elif name == "forwarded":
                    with lock:
                        k = next(made_up)
                    outcome = slow_body(port, local_stop, f"10.{k >> 16 & 255}.{k >> 8 & 255}.{k & 255}")
                else:
                    outcome = one_request(port, request)
            except OSError as exc:
                outcome = type(exc).__name__
                time.sleep(0.05)
            if outcome != "stopped":
                with lock:
                    counts[outcome] += 1

    threads = [threading.Thread(target=loop, daemon=True) for _ in range(connections)]
    for thread in threads:
        thread.start()
    stop.wait()
    local_stop.set()
    for thread in threads:
        thread.join(timeout=15)
    results.put(dict(counts))


# ------------------------------------------------------------------------------------------------ normal load
def normal_streams(
    url: str,
    sample: Path | None,
    streams: int,
    period_s: float,
    stop: multiprocessing.synchronize.Event,
    results: multiprocessing.queues.Queue[list[tuple[float, float, int]]],
) -> None:
    """Runs in its own process: `streams` threads, each one stream of full scans at the sensor's rate, each answer
    awaited; puts [(start monotonic, seconds, status), ...]."""
    import httpx

    scans = scans_from(sample)
    samples: list[tuple[float, float, int]] = []
    lock = threading.Lock()

    def stream(index: int) -> None:
        with httpx.Client(base_url=url, timeout=60.0) as http:
            next_at, k = time.perf_counter() + index * period_s / streams, 0
            while not stop.is_set():
                time.sleep(max(0.0, next_at - time.perf_counter()))
                start, started = time.perf_counter(), time.monotonic()
                fields = detect_client.FrameFields(k + 1, f"soak-{index}")
                body = detect_client.multipart_body(fields, scans[k % len(scans)])
                try:
                    status = http.post(
                        detect_client.detect_path(flow=False),
                        content=body.content,
                        headers={"content-type": body.content_type},
                    ).status_code
                except httpx.HTTPError:
                    status = -1
                with lock:
                    samples.append((started, time.perf_counter() - start, status))
                k += 1
                next_at = max(next_at + period_s, time.perf_counter())

    threads = [threading.Thread(target=stream, args=(i,), daemon=True) for i in range(streams)]
    for thread in threads:
        thread.start()
    stop.wait()
    for thread in threads:
        thread.join(timeout=60)
    results.put(samples)


def probe_readiness(
    url: str,
    stop: multiprocessing.synchronize.Event,
    results: multiprocessing.queues.Queue[list[tuple[float, float, int]]],
) -> None:
    """Runs in its own process: GET /health/ready every 50 ms; puts [(start monotonic, seconds, status), ...]."""
    import httpx

    probes = []
    with httpx.Client(base_url=url, timeout=10.0) as http:
        while not stop.is_set():
            start, started = time.perf_counter(), time.monotonic()
            try:
                status = http.get("/health/ready").status_code
            except httpx.HTTPError:
                status = -1
            probes.append((started, time.perf_counter() - start, status))
            stop.wait(READY_PROBE_PERIOD_S)
    results.put(probes)


# ------------------------------------------------------------------------------------------------ the run
@dataclass
class Phase:
    name: str
    windows: list[tuple[float, float]] = field(default_factory=list)
    attacker: collections.Counter[str] = field(default_factory=collections.Counter)

    def contains(self, t: float) -> bool:
        return any(start <= t < end for start, end in self.windows)


def run_block(
    phase: Phase, seconds: float, port: int, sample: Path | None, rss: list[tuple[float, int]], pid: int
) -> None:
    stop = multiprocessing.Event()
    results: multiprocessing.queues.Queue[dict[str, int]] = multiprocessing.Queue()
    attacker = None
    if phase.name in ATTACKS:
        attacker = multiprocessing.Process(target=attack, args=(phase.name, port, stop, results, sample))
        attacker.start()
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        time.sleep(1.0)
        rss.append((time.monotonic(), rss_bytes(pid)))
    phase.windows.append((start + SETTLE_S, time.monotonic()))
    if attacker is not None:
        stop.set()
        phase.attacker.update(results.get(timeout=120))
        attacker.join(timeout=30)


def summarise(
    phases: list[Phase], normal: list[tuple[float, float, int]], ready: list[tuple[float, float, int]]
) -> dict:
    rows = {}
    for phase in phases:
        lat = [1000 * s for t, s, status in normal if phase.contains(t) and status == 200]
        codes = collections.Counter(str(status) for t, _, status in normal if phase.contains(t))
        probes = [1000 * s for t, s, _ in ready if phase.contains(t)]
        ready_codes = collections.Counter(str(status) for t, _, status in ready if phase.contains(t))
        rows[phase.name] = {
            "requests": len([1 for t, _, _ in normal if phase.contains(t)]),
            "p50_ms": percentile(lat, 50),
            "p99_ms": percentile(lat, 99),
            "ready_p50_ms": percentile(probes, 50),
            "ready_p99_ms": percentile(probes, 99),
            "ready_max_ms": max(probes, default=float("nan")),
            "normal_codes": dict(codes),
            "ready_codes": dict(ready_codes),
            "attacker_codes": dict(phase.attacker),
        }
    return rows


def report(rows: dict, rss: list[tuple[float, int]], warm_rss: int) -> list[str]:
    quiet_p99 = rows["quiet"]["p99_ms"]
    print(
        f"{'phase':<12} {'requests':>8} {'p50 ms':>7} {'p99 ms':>7} {'vs quiet':>8} | {'ready p50':>9} {'p99':>6} "
        f"{'max':>6} | normal answers | attacker answers"
    )
    failed = []
    for name, row in rows.items():
        ratio = row["p99_ms"] / quiet_p99 if name != "quiet" else 1.0
        print(
            f"{name:<12} {row['requests']:>8} {row['p50_ms']:>7.1f} {row['p99_ms']:>7.1f} {ratio:>7.2f}x | "
            f"{row['ready_p50_ms']:>9.1f} {row['ready_p99_ms']:>6.1f} {row['ready_max_ms']:>6.1f} | "
            f"{row['normal_codes']} | {row['attacker_codes'] or '-'}"
        )
        if name != "quiet":
            if ratio > P99_RATIO_LIMIT:
                failed.append(f"{name}: normal p99 {ratio:.2f}x the quiet p99 (limit {P99_RATIO_LIMIT}x)")
            if row["ready_p99_ms"] > READY_LIMIT_MS:
                failed.append(f"{name}: readiness p99 {row['ready_p99_ms']:.1f} ms (limit {READY_LIMIT_MS} ms)")
        if set(row["normal_codes"]) - {"200"}:
            failed.append(f"{name}: normal requests answered {row['normal_codes']}")
        if set(row["ready_codes"]) - {"200"}:
            failed.append(f"{name}: readiness answered {row['ready_codes']}")
        fives = {k: v for k, v in row["attacker_codes"].items() if k.startswith("5")}
        if fives:
            failed.append(f"{name}: attackers got {fives}")
    end_rss = rss[-1][1]
    growth = end_rss / warm_rss - 1.0
    print(
        f"server RSS: {warm_rss / 2**20:.0f} MiB after warm-up, {end_rss / 2**20:.0f} MiB at the end "
        f"({100 * growth:+.1f}%), highest {max(r for _, r in rss) / 2**20:.0f} MiB"
    )
    if growth > RSS_GROWTH_LIMIT:
        failed.append(f"RSS grew {100 * growth:.1f}% after warm-up (limit {100 * RSS_GROWTH_LIMIT:.0f}%)")
    return failed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.hostile_soak", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sample",
        type=Path,
        default=os.environ.get("RAFD_RADIATE_SAMPLE") or None,
        help="RADIATE sequence for the normal streams (default: $RAFD_RADIATE_SAMPLE, else speckle)",
    )
    parser.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped one)")
    parser.add_argument("--minutes", type=float, default=5.0, help="bounded run time (hours are fine: 240)")
    parser.add_argument("--block-seconds", type=float, default=15.0, help="length of each quiet or attack block")
    parser.add_argument("--streams", type=int, default=2, help="normal streams (the held load)")
    parser.add_argument("--rate-hz", type=float, default=4.0, help="frames per second per normal stream")
    parser.add_argument(
        "--attacks", default=",".join(DEFAULT_ATTACKS), help="comma-separated, from " + ", ".join(ATTACKS)
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the figures to this file")
    args = parser.parse_args(argv)
    attacks = [a for a in args.attacks.split(",") if a]
    if (
        not attacks
        or set(attacks) - set(ATTACKS)
        or not 0.5 <= args.minutes <= 24 * 60
        or not 5 <= args.block_seconds <= 600
        or not 1 <= args.streams <= 16
        or not 0 < args.rate_hz <= 20
    ):
        parser.error("bounded load only: --minutes 0.5-1440, --block-seconds 5-600, --streams 1-16, --rate-hz <= 20")

    port = free_port()
    url = f"http://{HOST}:{port}"
    server = subprocess.Popen(
        serve_command(port, model=args.model), env={k: v for k, v in os.environ.items() if not k.startswith("RAFD_")}
    )

    def give_up() -> None:
        server.kill()
        os._exit(2)

    watchdog = threading.Timer(60 * args.minutes + 600, give_up)
    watchdog.daemon = True
    watchdog.start()
    stop = multiprocessing.Event()
    normal_q: multiprocessing.queues.Queue[list[tuple[float, float, int]]] = multiprocessing.Queue()
    ready_q: multiprocessing.queues.Queue[list[tuple[float, float, int]]] = multiprocessing.Queue()
    try:
        wait_ready(url, server, timeout=300.0)
        print(
            f"rafd-serve on {url}; {args.streams} normal streams of full scans at {args.rate_hz} Hz "
            f"({'RADIATE sample' if args.sample else 'speckle stand-ins'}); attacks {attacks} from {ATTACKER}; "
            f"{args.block_seconds:g} s blocks for {args.minutes:g} min; {usable_cpus()} usable CPUs"
        )
        loader = multiprocessing.Process(
            target=normal_streams, args=(url, args.sample, args.streams, 1.0 / args.rate_hz, stop, normal_q)
        )
        prober = multiprocessing.Process(target=probe_readiness, args=(url, stop, ready_q))
        loader.start()
        prober.start()
        rss: list[tuple[float, int]] = []
        # Warm-up (not measured): the normal load, then each attack for a few seconds, so that RSS after it
        # includes what every kind of request allocates once (buffers, executor threads, the allocator's arenas).
        run_block(Phase("warm-up"), min(args.block_seconds, 15.0), port, args.sample, rss, server.pid)
        for name in attacks:
            run_block(Phase(name), WARM_UP_ATTACK_S, port, args.sample, rss, server.pid)
        warm_rss = rss[-1][1]
        phases = {name: Phase(name) for name in ("quiet", *attacks)}
        deadline = time.monotonic() + 60 * args.minutes
        rounds = 0
        while rounds == 0 or time.monotonic() + 2 * len(attacks) * args.block_seconds <= deadline:
            for name in attacks:
                run_block(phases["quiet"], args.block_seconds, port, args.sample, rss, server.pid)
                run_block(phases[name], args.block_seconds, port, args.sample, rss, server.pid)
            rounds += 1
        stop.set()
        normal, ready = normal_q.get(timeout=120), ready_q.get(timeout=120)
        loader.join(timeout=60)
        prober.join(timeout=60)
    finally:
        stop.set()
        watchdog.cancel()
        server.terminate()
        server.wait(timeout=60)
    rows = summarise(list(phases.values()), normal, ready)
    served = sum(1 for _, _, status in normal if status == 200)
    print(f"{rounds} rounds; normal requests served: {served} of {len(normal)} (warm-up included)")
    failed = report(rows, rss, warm_rss)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "rss": rss, "warm_rss": warm_rss, "rounds": rounds}, indent=1))
    for reason in failed:
        print(f"FAILED: {reason}")
    print("PASSED" if not failed else "")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
