"""`python -m tools.fault_drill [--replicas 3] [--streams 3] [--frames 24] [--keepalive-posts 8]`: a fault drill of
the shipped scale-out (deploy/nginx.conf on loopback in front of rafd-serve replicas, bench/loopback.py).

M streams post at the radar's 4 Hz through nginx (X-Stream-Id, `previous_timestamp`, retries with backoff as
`rafd client` does: rafd.cli.client.post_with_retries) while faults are injected, one scenario at a time:

- baseline: no fault;
- kill -9 idle: every stream paused until nothing is in flight, stream 0's replica SIGKILLed, streams resumed;
- kill -9 in flight: stream 0's replica SIGKILLed 20 ms after stream 0 started posting a frame;
- SIGTERM: stream 0's replica stopped gracefully mid-run;
- restart: stream 0's replica stopped (SIGTERM) and started again at once (a fresh process, no streams);
- keep-alive: one stream posting every `--keepalive-spacing` seconds (5 s: uvicorn's own idle timeout, the race of
  issue 39), through nginx's kept-alive upstream connections;
- returning stream: the issue's reproduction on the replicas directly: frames 1-8 to replica 0, 9-12 to replica 1,
  13-16 back to replica 0 (a failover and a return), with and without `previous_timestamp`.

Stopped replicas are started again after each scenario, and the next waits out nginx's fail_timeout (10 s). Per
scenario it prints: answers by HTTP code (every attempt), connection errors, retries, frames lost (never answered
after the retries), wrong-chain answers (an answer whose `frames_used` exceeds the frames its replica really got in a
row from that stream since its last restart), chains restarted by the service, and the longest outage of a stream
(seconds between two answers beyond the 0.25 s period). Frames are synthetic 256 px scans (the model's input size)
with poses, so the drill measures routing and failover rather than the model. Exit status 1 when a target is missed
(any wrong-chain answer, any frame lost, any 502 in the keep-alive scenario).
"""

from __future__ import annotations

import argparse
import json
import secrets
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.loopback import LoopbackCluster
from rafd import detect_client
from rafd.cli.client import RETRY_STATUSES, RetryableError, ServiceError, post_with_retries

PERIOD = 0.25  # a 4 Hz radar
NUM_FRAMES = 4  # the shipped model's buffer
FAIL_TIMEOUT_S = 10.5  # nginx.conf's fail_timeout (10 s), and a little
PINNED = {"RAFD_RUNTIME": "onnxruntime", "RAFD_PRECISION": "fp32", "RAFD_THREADS": "1", "RAFD_CONCURRENT_RUNS": "1"}


def slug(name: str) -> str:
    """A scenario's name as a stream id part: every scenario posts to streams of its own."""
    return "".join(c if c.isalnum() else "_" for c in name)


def synthetic_png(stream: int, k: int, size: int = 256) -> bytes:
    """A scan-like frame: speckle plus a few bright blocks that move with the frame number."""
    rng = np.random.default_rng(1000 * stream + k)
    image = (rng.random((size, size)) * 40).astype(np.uint8)
    for j in range(4):
        row, col = (37 * j + 3 * k) % (size - 8), (53 * j + 11 * stream) % (size - 8)
        image[row : row + 6, col : col + 6] = 220
    ok, encoded = cv2.imencode(".png", image)
    assert ok
    return encoded.tobytes()


@dataclass
class Frame:
    k: int
    timestamp: float
    answer: dict[str, Any] | None = None
    replica: str | None = None  # the address that answered (X-RaFD-Replica's last, or the direct URL)
    sent_at: float = 0.0
    answered_at: float | None = None


@dataclass
class Tally:
    """What one scenario saw, all streams together."""

    codes: Counter[int] = field(default_factory=Counter)
    error_codes: Counter[str] = field(default_factory=Counter)  # the JSON error code of each error ("not JSON")
    connection_errors: int = 0
    retries: int = 0
    streams: list[list[Frame]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def attempt(self, status: int | None) -> None:
        with self.lock:
            if status is None:
                self.connection_errors += 1
            else:
                self.codes[status] += 1


def post(url: str, stream_id: str, frame: Frame, png: bytes, previous: float | None, tally: Tally) -> None:
    """One attempt: fills `frame` on a 200; RetryableError on 502/503/504 or a lost connection; ServiceError else."""
    fields = detect_client.FrameFields(frame.timestamp, None, (0.0, 2.0 * frame.k, 0.0), previous_timestamp=previous)
    body = detect_client.json_body(fields, detect_client.base64_png(png))
    request = detect_client.detect_request(body, header_stream_id=stream_id)
    try:
        with detect_client.post(url, request, timeout=30.0) as response:
            answer = json.loads(response.read())
            replica = response.headers.get("X-RaFD-Replica")
        tally.attempt(200)
    except urllib.error.HTTPError as exc:
        tally.attempt(exc.code)
        text = exc.read()[:600].decode("utf-8", "replace")
        try:
            code = str(json.loads(text)["error"]["code"])
        except (ValueError, KeyError, TypeError):
            code = "not JSON"
        with tally.lock:
            tally.error_codes[code] += 1
        if exc.code in RETRY_STATUSES:
            raise RetryableError(f"HTTP {exc.code}: {text}") from exc
        raise ServiceError(f"HTTP {exc.code}: {text}") from exc
    except (urllib.error.URLError, ConnectionError, TimeoutError, OSError) as exc:
        tally.attempt(None)
        raise RetryableError(f"connection: {exc}") from exc
    frame.answer = answer
    frame.replica = replica.split(", ")[-1] if replica else url
    frame.answered_at = time.monotonic()


class Pause:
    """Lets the fault injector stop every stream between frames and wait until nothing is in flight."""

    def __init__(self) -> None:
        self.running = threading.Event()
        self.running.set()
        self.in_flight = 0
        self.lock = threading.Lock()

    def enter(self) -> None:
        self.running.wait(timeout=60.0)
        with self.lock:
            self.in_flight += 1

    def leave(self) -> None:
        with self.lock:
            self.in_flight -= 1

    def quiet(self, timeout: float = 30.0) -> None:
        self.running.clear()
        deadline = time.monotonic() + timeout
        while self.in_flight and time.monotonic() < deadline:
            time.sleep(0.005)


def run_stream(
    urls: Callable[[int], str],
    stream: int,
    stream_id: str,
    count: int,
    tally: Tally,
    retries: int,
    spacing: float = PERIOD,
    send_previous: bool = True,
    pause: Pause | None = None,
    on_send: Callable[[int, list[Frame]], None] | None = None,
) -> list[Frame]:
    """Post `count` frames at `spacing` seconds (real time and timestamps alike), each retried as rafd client does."""
    frames: list[Frame] = []
    previous: float | None = None
    start = time.monotonic()
    base = 1_700_000_000.0 + 10.0 * stream
    for k in range(count):
        delay = start + k * spacing - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        frame = Frame(k, base + k * spacing)
        frames.append(frame)
        png = synthetic_png(stream, k)
        if pause is not None:
            pause.enter()
        try:
            frame.sent_at = time.monotonic()
            if on_send is not None:
                on_send(k, frames)
            _, used = post_with_retries(
                retries,
                lambda: post(urls(k), stream_id, frame, png, previous if send_previous else None, tally),  # noqa: B023
                f"{stream_id} frame {k}",
                log=lambda line: None,
            )
            with tally.lock:
                tally.retries += used
            previous = frame.timestamp
        except ServiceError as exc:
            print(f"  {stream_id} frame {k} lost: {exc}", file=sys.stderr)
        finally:
            if pause is not None:
                pause.leave()
    with tally.lock:
        tally.streams.append(frames)
    return frames


def wrong_chain(frames: list[Frame]) -> tuple[int, int]:
    """(wrong-chain answers, restarts) of one stream: an answer is wrong when its frames_used exceeds the frames its
    replica got in a row from this stream (a frame never answered counts as possibly got: an upper bound), since
    the replica's last restart of the chain. Replays are the same frame and count once."""
    wrong = restarts = 0
    run, last = 0, None
    for frame in frames:
        answer = frame.answer
        if answer is None:
            run += 1
            continue
        run = run + 1 if frame.replica == last else 1
        if answer.get("stream_restarted"):
            restarts += 1
            run = 1
        if answer["frames_used"] > min(NUM_FRAMES, run):
            wrong += 1
        last = frame.replica
    return wrong, restarts


def outage_s(frames: list[Frame]) -> float:
    times = [f.answered_at for f in frames if f.answered_at is not None]
    gaps = [b - a for a, b in zip(times, times[1:])]
    return max(0.0, max(gaps, default=0.0) - PERIOD)


@dataclass(frozen=True)
class Result:
    name: str
    codes: dict[int, int]
    error_codes: dict[str, int]
    connection_errors: int
    retries: int
    frames: int
    lost: int
    wrong_chain: int
    restarts: int
    outage_s: float

    def line(self) -> str:
        codes = ", ".join(f"{code}: {n}" for code, n in sorted(self.codes.items()))
        errors = f" ({', '.join(f'{c}: {n}' for c, n in sorted(self.error_codes.items()))})" if self.error_codes else ""
        return (
            f"{self.name:<26} answers {{{codes}}}{errors}  connection errors {self.connection_errors}  "
            f"retries {self.retries}  "
            f"frames {self.frames}  lost {self.lost}  wrong-chain {self.wrong_chain}  restarts {self.restarts}  "
            f"longest outage {self.outage_s:.2f} s"
        )


def summarise(name: str, tally: Tally) -> Result:
    frames = [f for stream in tally.streams for f in stream]
    chains = [wrong_chain(stream) for stream in tally.streams]
    return Result(
        name,
        dict(tally.codes),
        dict(tally.error_codes),
        tally.connection_errors,
        tally.retries,
        len(frames),
        sum(f.answer is None for f in frames),
        sum(w for w, _ in chains),
        sum(r for _, r in chains),
        round(max((outage_s(s) for s in tally.streams), default=0.0), 2),
    )


class Drill:
    def __init__(self, cluster: LoopbackCluster, streams: int, frames: int, retries: int) -> None:
        self.cluster = cluster
        self.streams = streams
        self.frames = frames
        self.retries = retries
        self.run_id = secrets.token_hex(3)

    def replica_of(self, frames: list[Frame]) -> int:
        """The index of the replica that answered the stream's last answered frame."""
        for frame in reversed(frames):
            if frame.replica is not None:
                for index in range(self.cluster.replicas):
                    if frame.replica == self.cluster.replica_address(index):
                        return index
        raise RuntimeError("stream 0 has no answer yet")

    def restore(self, faulted: bool) -> None:
        """Every replica running again; after a fault, wait out nginx's fail_timeout: the next scenario starts clean."""
        for index, process in enumerate(self.cluster.processes):
            if process.poll() is not None:
                self.cluster.restart(index)
        if faulted:
            time.sleep(FAIL_TIMEOUT_S)

    def through_nginx(
        self, name: str, fault: Callable[[list[Frame], Pause], None] | None = None, fault_at: int = 0
    ) -> Result:
        tally, pause = Tally(), Pause()
        done = threading.Event()
        holder: list[list[Frame]] = []

        def on_send(k: int, frames: list[Frame]) -> None:
            if not holder:
                holder.append(frames)
            if k == fault_at and fault is not None and not done.is_set():
                done.set()
                threading.Thread(target=fault, args=(frames, pause), daemon=True).start()

        threads = [
            threading.Thread(
                target=run_stream,
                args=(lambda k: self.cluster.url, s, f"{slug(name)}-{self.run_id}-{s}", self.frames, tally),
                kwargs={"retries": self.retries, "pause": pause, "on_send": on_send if s == 0 else None},
            )
            for s in range(self.streams)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=600.0)
        result = summarise(name, tally)
        self.restore(faulted=fault is not None)
        return result

    # ---------------------------------------------------------------- faults (run in their own thread)
    def kill_idle(self, frames: list[Frame], pause: Pause) -> None:
        index = self.replica_of(frames[:-1])
        pause.quiet()
        self.cluster.kill(index)
        pause.running.set()

    def kill_in_flight(self, frames: list[Frame], pause: Pause) -> None:
        index = self.replica_of(frames[:-1])
        time.sleep(0.02)  # stream 0's frame is on its way or being processed
        self.cluster.kill(index)

    def sigterm(self, frames: list[Frame], pause: Pause) -> None:
        self.cluster.terminate(self.replica_of(frames[:-1]))

    def restart(self, frames: list[Frame], pause: Pause) -> None:
        index = self.replica_of(frames[:-1])
        self.cluster.terminate(index)
        self.cluster.restart(index)

    # ---------------------------------------------------------------- the other scenarios
    def keep_alive(self, posts: int, spacing: float) -> Result:
        tally = Tally()
        run_stream(lambda k: self.cluster.url, 0, f"keepalive-{self.run_id}", posts, tally, self.retries, spacing)
        return summarise(f"keep-alive ({spacing:g} s apart)", tally)

    def returning(self, send_previous: bool) -> Result:
        """Frames 1-8 to replica 0, 9-12 to replica 1, 13-16 back to replica 0, posted to the replicas directly."""
        tally = Tally()
        direct = [f"http://127.0.0.1:{port}" for port in self.cluster.replica_ports]

        def url(k: int) -> str:
            return direct[1] if 8 <= k < 12 else direct[0]

        label = "with" if send_previous else "without"
        stream_id = f"returning-{label}-{self.run_id}"
        run_stream(url, 0, stream_id, 16, tally, self.retries, send_previous=send_previous)
        return summarise(f"returning ({label} prev.)", tally)


def run(args: argparse.Namespace) -> list[Result]:
    env = {**PINNED, "OMP_NUM_THREADS": "1"}
    if args.replica_keep_alive_s is not None:
        env["RAFD_KEEP_ALIVE_TIMEOUT_S"] = str(args.replica_keep_alive_s)
    work = Path(args.work or tempfile.mkdtemp(prefix="rafd-fault-drill-"))
    results = []
    with LoopbackCluster(args.replicas, work, env) as cluster:
        drill = Drill(cluster, args.streams, args.frames, args.retries)
        at = args.frames // 3
        plan: list[tuple[str, Callable[[], Result]]] = [
            ("baseline", lambda: drill.through_nginx("baseline")),
            ("kill9-idle", lambda: drill.through_nginx("kill -9 idle", drill.kill_idle, at)),
            ("kill9-inflight", lambda: drill.through_nginx("kill -9 in flight", drill.kill_in_flight, at)),
            ("sigterm", lambda: drill.through_nginx("SIGTERM", drill.sigterm, at)),
            ("restart", lambda: drill.through_nginx("restart", drill.restart, at)),
            ("keepalive", lambda: drill.keep_alive(args.keepalive_posts, args.keepalive_spacing)),
            ("returning", lambda: drill.returning(True)),
            ("returning-old-client", lambda: drill.returning(False)),
        ]
        for key, scenario in plan:
            if args.only and key not in args.only:
                continue
            result = scenario()
            print(result.line(), flush=True)
            results.append(result)
    return results


def targets_missed(results: list[Result]) -> list[str]:
    missed = []
    for r in results:
        if r.wrong_chain:
            missed.append(f"{r.name}: {r.wrong_chain} wrong-chain answers")
        if r.lost:
            missed.append(f"{r.name}: {r.lost} frames lost")
        if r.name.startswith("keep-alive") and r.codes.get(502):
            missed.append(f"{r.name}: {r.codes[502]} keep-alive 502s")
        if r.error_codes.get("not JSON"):
            missed.append(f"{r.name}: {r.error_codes['not JSON']} errors not in the service's JSON shape")
    return missed


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m tools.fault_drill", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--replicas", type=int, default=3, help="rafd-serve replicas behind nginx (default 3)")
    parser.add_argument("--streams", type=int, default=3, help="streams posting at 4 Hz at once (default 3)")
    parser.add_argument("--frames", type=int, default=24, help="frames per stream per scenario (default 24: 6 s)")
    parser.add_argument("--retries", type=int, default=4, help="retries per frame, as rafd client's --retries")
    parser.add_argument("--keepalive-posts", type=int, default=8, help="posts of the keep-alive scenario (default 8)")
    parser.add_argument(
        "--keepalive-spacing", type=float, default=5.0, help="seconds between them (default 5: uvicorn's own timeout)"
    )
    parser.add_argument(
        "--replica-keep-alive-s",
        type=float,
        default=None,
        help="RAFD_KEEP_ALIVE_TIMEOUT_S of the replicas (default: the service's, 75 s; 5 reproduces the race)",
    )
    parser.add_argument("--only", nargs="*", default=None, help="scenario keys to run (default: all)")
    parser.add_argument("--work", default=None, help="folder for nginx's and the replicas' files and logs")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    results = run(args)
    missed = targets_missed(results)
    for line in missed:
        print(f"target missed: {line}")
    if not missed:
        print("targets met: 0 wrong-chain answers, 0 frames lost, 0 keep-alive 502s")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
