"""A real uvicorn server on loopback serving the FakeRunner app: frames over HTTP, then a clean shutdown."""

from __future__ import annotations

import httpx
import pytest

from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import blob_frame, detect_json, png, serve_in_thread, wait_ready

pytestmark = pytest.mark.network


def test_real_server_streams_frames_and_enforces_the_limit_on_chunked_bodies():
    # frames 1 s apart, then 6 s: the staleness rule (RAFD_STREAM_GAP_RESTART_S) off, the buffer is what is tested
    settings = Settings(threads=1, max_request_bytes=100_000, stream_gap_restart_s=0)
    app = create_app(settings, runner=FakeRunner())
    with serve_in_thread(app) as url, httpx.Client(base_url=url, timeout=10.0) as http:
        wait_ready(http)
        assert http.get("/health/live").json() == {"status": "alive"}
        for t in range(5):
            frame = blob_frame(128, [(8 + 4 * t, 8, 255)])
            answer = http.post("/detect", json=detect_json("road", 50.0 + t, frame, (t, 0.0, 0.0)))
            assert answer.status_code == 200, answer.text
            assert answer.json()["frames_used"] == min(t + 1, 4)
        files = {"image": ("f.png", png(blob_frame(128, [])), "image/png")}
        form = http.post(
            "/detect",
            data={"stream_id": "road", "timestamp": "60", "pose_x": "5", "pose_y": "0", "pose_yaw": "0"},
            files=files,
        )
        assert form.status_code == 200 and form.json()["warming_up"] is False
        chunked = http.post(
            "/detect", content=(b"x" * 10_000 for _ in range(20)), headers={"content-type": "application/json"}
        )
        assert "content-length" not in chunked.request.headers
        assert chunked.status_code == 413 and chunked.json()["error"]["code"] == "request_too_large"
        streams = http.get("/streams").json()
        assert streams["count"] == 1 and streams["streams"][0]["last_timestamp"] == 60.0
        assert 'route="/detect"' in http.get("/metrics").text
