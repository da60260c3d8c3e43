"""How many radars one replica holds: N streams posting at the sensor's rate, open loop, against a running service.

Each stream posts one frame every `period_s` (a Navtech scan: 0.25 s) on its own schedule, the N schedules spread
evenly over the period, whether or not its previous answer has come back (a sensor does not wait); each request runs
on its own connection. A level holds when every answer is 200 and the p99 latency (from the moment a frame was due
to its answer) is within the budget; `find_capacity` raises N until a level fails and reports the largest that held.
Frames are real scans played forward then backward (smooth ego motion for the service's odometry), encoded before
the clock starts: full scans or model-size crops, as PNG in a JSON body (base64) or multipart, with or without poses.
Standard library and numpy only (the service runs in its own process).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.timing import percentile
from rafd import detect_client
from rafd.preprocess import model_crop

STAGES = ("read_ms", "decode_ms", "wait_ms", "odometry_ms", "model_ms", "post_ms", "total_ms")


def looped_scans(sample: Path, count: int = 18) -> list[np.ndarray]:
    """A RADIATE sequence's Cartesian scans played forward then backward (the ego's motion stays smooth)."""
    paths = sorted((Path(sample) / "Navtech_Cartesian").glob("*.png"))[:count]
    if len(paths) < 2:
        raise FileNotFoundError(f"no Navtech_Cartesian/*.png scans under {sample}")
    scans = []
    for path in paths:
        scan = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if scan is None:
            raise FileNotFoundError(f"{path} is not a readable PNG")
        scans.append(scan)
    return scans + scans[-2:0:-1]


@dataclass(frozen=True)
class Frames:
    """Pre-encoded request bodies of one input form."""

    bodies: list[bytes]  # PNG bytes per frame
    size: int  # posted side in pixels
    label: str


def encode_frames(scans: Sequence[np.ndarray], crop: int | None = None) -> Frames:
    """PNG bytes of every scan, whole or centre-cropped to `crop` pixels (the model's input size)."""
    bodies = [detect_client.png_bytes(scan if crop is None else model_crop(scan, crop)) for scan in scans]
    size = scans[0].shape[0] if crop is None else crop
    return Frames(bodies, size, f"{size} px {'scans' if crop is None else 'crops'}")


@dataclass
class Level:
    """One load level's outcome."""

    streams: int
    latencies_s: list[float] = field(default_factory=list)
    statuses: dict[int, int] = field(default_factory=dict)
    timings: list[dict[str, float]] = field(default_factory=list)  # the answers' own timing fields
    errors: list[str] = field(default_factory=list)

    @property
    def requests(self) -> int:
        return sum(self.statuses.values())

    def p(self, q: float) -> float:
        return 1e3 * percentile(self.latencies_s, q)

    def held(self, budget_ms: float) -> bool:
        return self.requests > 0 and set(self.statuses) == {200} and self.p(99) <= budget_ms

    def stage(self, name: str, q: float = 50) -> float:
        return percentile([t[name] for t in self.timings if name in t], q)

    def summary(self) -> dict[str, Any]:
        return {
            "streams": self.streams,
            "requests": self.requests,
            "statuses": dict(self.statuses),
            "p50_ms": round(self.p(50), 1),
            "p99_ms": round(self.p(99), 1),
            "stages_p50_ms": {s: round(self.stage(s), 1) for s in STAGES},
            "stages_p99_ms": {s: round(self.stage(s, 99), 1) for s in STAGES},
        }


def _request(
    png: bytes, stream: str, timestamp: float, pose: tuple[float, float, float] | None, multipart: bool
) -> detect_client.DetectRequest:
    """One POST /detect of the load, without the flow (the answer's flow is not what is measured)."""
    fields = detect_client.FrameFields(timestamp, stream, pose)
    body = (
        detect_client.multipart_body(fields, png)
        if multipart
        else detect_client.json_body(fields, detect_client.base64_png(png))
    )
    return detect_client.detect_request(body, flow=False)


def run_level(
    url: str,
    frames: Frames,
    streams: int,
    seconds: float,
    period_s: float = 0.25,
    poses: np.ndarray | None = None,
    multipart: bool = False,
    tag: str = "cap",
) -> Level:
    """`streams` streams at 1 / period_s frames per second for `seconds`, open loop -> the level's outcome."""
    level = Level(streams)
    lock = threading.Lock()
    count = max(1, int(round(seconds / period_s)))
    requests: list[tuple[float, detect_client.DetectRequest]] = []  # (due offset s, request)
    run_id = f"{tag}-{int(time.time() * 1000) % 10**9}-{streams}"
    for s in range(streams):
        for k in range(count):
            j = k % len(frames.bodies)
            pose = None if poses is None else detect_client.pose_of(poses[j])
            due = (s / streams + k) * period_s
            requests.append((due, _request(frames.bodies[j], f"{run_id}-{s}", 1000.0 + k * period_s, pose, multipart)))
    requests.sort(key=lambda r: r[0])

    def post(due: float, request: detect_client.DetectRequest, start: float) -> None:
        connection = detect_client.connect(
            url, timeout=120.0
        )  # one per request: a sensor's frames do not wait for each other
        try:
            status, text = detect_client.exchange(connection, request)
            elapsed = time.perf_counter() - (start + due)
            with lock:
                level.statuses[status] = level.statuses.get(status, 0) + 1
                level.latencies_s.append(elapsed)
                if status == 200:
                    level.timings.append(json.loads(text)["timing"])
                elif len(level.errors) < 5:
                    level.errors.append(text[:200].decode(errors="replace"))
        except OSError as error:
            with lock:
                level.statuses[0] = level.statuses.get(0, 0) + 1
                if len(level.errors) < 5:
                    level.errors.append(f"{type(error).__name__}: {error}")
        finally:
            connection.close()

    threads = []
    start = time.perf_counter()
    for due, request in requests:
        delay = start + due - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        thread = threading.Thread(target=post, args=(due, request, start), daemon=True)
        thread.start()
        threads.append(thread)
    for thread in threads:
        thread.join(timeout=180.0)
    return level


def find_capacity(
    url: str,
    frames: Frames,
    budget_ms: float = 250.0,
    seconds: float = 10.0,
    poses: np.ndarray | None = None,
    multipart: bool = False,
    start: int = 1,
    limit: int = 64,
    log: Any = print,
) -> tuple[int, list[Level]]:
    """Raise the number of streams (1, 2, 4, then +2 up to 16, then +4) until a level fails -> (the largest N that
    held, every level run); then the one between the last that held and the first that failed, when it is untried."""
    levels: list[Level] = []
    held_at = 0
    n = start
    while n <= limit:
        level = run_level(url, frames, n, seconds, poses=poses, multipart=multipart)
        levels.append(level)
        log(f"  {n} streams: p50 {level.p(50):.0f} ms, p99 {level.p(99):.0f} ms, statuses {level.statuses}")
        if not level.held(budget_ms):
            if n - held_at > 1:
                middle = (n + held_at) // 2
                if middle > held_at:
                    between = run_level(url, frames, middle, seconds, poses=poses, multipart=multipart)
                    levels.append(between)
                    log(
                        f"  {middle} streams: p50 {between.p(50):.0f} ms, p99 {between.p(99):.0f} ms, statuses "
                        f"{between.statuses}"
                    )
                    if between.held(budget_ms):
                        held_at = middle
            break
        held_at = n
        n = n * 2 if n < 4 else (n + 2 if n < 16 else n + 4)
        time.sleep(1.0)  # the service's queues drain between levels
    return held_at, levels
