"""HTTP load on POST /detect: client threads, each keeping one plain `http.client` connection to its own stream, so
the latency measured is the service's, not a client library's (httpx adds about 1 ms per request)."""

from __future__ import annotations

import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from rafd import detect_client
from rafd.protocol import stream_id_from


def encode_png(image: np.ndarray) -> str:
    """uint8 image -> base64 PNG text, as JSON bodies carry it."""
    return detect_client.base64_png(detect_client.png_bytes(image))


def load_streams(url: str, bodies: list[str], poses: np.ndarray, streams: int, frames: int, tag: str) -> dict[str, Any]:
    """`streams` client threads, each posting `frames` frames (base64 PNGs `bodies`, poses [N, 3]) of its own stream
    back to back; bodies are encoded before the clock starts. -> {latencies (s), answers, fps}; RuntimeError naming
    the count and the first failure when any request was not answered 200."""
    latencies: list[float] = []
    answers: list[dict[str, Any]] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(index: int) -> None:
        connection = detect_client.connect(url, timeout=120.0)
        stream_id = stream_id_from(f"bench-{tag}-{streams}-{index}")
        try:
            for k in range(frames):
                j = k % len(bodies)
                fields = detect_client.FrameFields(1000.0 + k * 0.25, stream_id, detect_client.pose_of(poses[j]))
                request = detect_client.detect_request(detect_client.json_body(fields, bodies[j]))
                start = time.perf_counter()
                status, text = detect_client.exchange(connection, request)
                elapsed = time.perf_counter() - start
                with lock:
                    if status != 200:
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
