"""HTTP load on POST /detect: client threads, each keeping one plain `http.client` connection to its own stream, so
the latency measured is the service's, not a client library's (httpx adds about 1 ms per request)."""

from __future__ import annotations

import base64
import http.client
import json
import re
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any
from urllib.parse import urlsplit

import cv2
import numpy as np

STREAM_ID_UNSAFE = re.compile(r"[^A-Za-z0-9._~:@+-]")


def encode_png(image: np.ndarray) -> str:
    """uint8 image -> base64 PNG text, as JSON bodies carry it."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return base64.b64encode(data.tobytes()).decode("ascii")


def load_streams(url: str, bodies: list[str], poses: np.ndarray, streams: int, frames: int, tag: str) -> dict[str, Any]:
    """`streams` client threads, each posting `frames` frames (base64 PNGs `bodies`, poses [N, 3]) of its own stream
    back to back; bodies are encoded before the clock starts. -> {latencies (s), answers, fps}; RuntimeError naming
    the count and the first failure when any request was not answered 200."""
    address = urlsplit(url)
    latencies: list[float] = []
    answers: list[dict[str, Any]] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(index: int) -> None:
        connection = http.client.HTTPConnection(address.hostname or "127.0.0.1", address.port, timeout=120.0)
        try:
            for k in range(frames):
                j = k % len(bodies)
                body = {
                    "stream_id": STREAM_ID_UNSAFE.sub("_", f"bench-{tag}-{streams}-{index}"),
                    "timestamp": 1000.0 + k * 0.25,
                    "pose": {"x": float(poses[j, 0]), "y": float(poses[j, 1]), "yaw": float(poses[j, 2])},
                    "image": bodies[j],
                }
                raw = json.dumps(body).encode()
                start = time.perf_counter()
                connection.request("POST", "/detect", raw, {"Content-Type": "application/json"})
                response = connection.getresponse()
                text = response.read()
                elapsed = time.perf_counter() - start
                with lock:
                    if response.status != 200:
                        errors.append(text[:200].decode(errors="replace"))
                    else:
                        latencies.append(elapsed)
                        answers.append(json.loads(text))
        finally:
            connection.close()

    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=streams) as pool:
        list(pool.map(client, range(streams)))  # list(): a client's exception surfaces here
    wall = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"{len(errors)} failed requests, first: {errors[0]}")
    return {"latencies": latencies, "answers": answers, "fps": len(latencies) / wall}
