"""rafd-client against a real uvicorn server running the service with the FakeRunner."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.cli.client import main

POSES = np.array([[0.0, 0.0, 0.0], [0.5, 1.0, 0.01], [1.0, 2.0, 0.02]])


def red_pixels_along(picture: np.ndarray, polygon: np.ndarray) -> float:
    """Fraction of points sampled along a [4, 2] outline whose pixel (or a neighbour) is prediction red."""
    red = (picture[..., 2] > 180) & (picture[..., 1] < 90) & (picture[..., 0] < 90)
    hits = []
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        for t in np.linspace(0.1, 0.9, 9):
            u, v = np.floor(a + t * (b - a)).astype(int)
            hits.append(red[max(v - 1, 0) : v + 2, max(u - 1, 0) : u + 2].any())
    return float(np.mean(hits))


@pytest.fixture
def sequence(tmp_path: Path) -> Path:
    """A 3-frame RADIATE-format folder: full 1152 scans with a bright car near the radar, plus ego_poses.csv."""
    root = tmp_path / "city_7_0"
    (root / "Navtech_Cartesian").mkdir(parents=True)
    lines, rows = [], ["frame,timestamp,x,y,yaw"]
    for n in range(1, 4):
        scan = np.zeros((1152, 1152), np.uint8)
        scan[560 - 8 * n : 572 - 8 * n, 600:608] = 255
        cv2.imwrite(str(root / "Navtech_Cartesian" / f"{n:06d}.png"), scan)
        stamp = 1574859771.25 + 0.25 * n
        lines.append(f"Frame: {n:06d} Time: {stamp:.9f}")
        rows.append(f"{n},{stamp},{POSES[n - 1][0]},{POSES[n - 1][1]},{POSES[n - 1][2]}")
    (root / "Navtech_Cartesian.txt").write_text("\n".join(lines) + "\n")
    (root / "ego_poses.csv").write_text("\n".join(rows) + "\n")
    (root / "meta.json").write_text(json.dumps({"name": "city_7_0", "type": "city", "set": "test"}))
    (root / "annotations").mkdir()
    (root / "annotations" / "annotations.json").write_text("[]")
    return root


def test_client_streams_a_sequence_and_writes_drawings_and_video(sequence, service_url, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(sequence), "--url", service_url, "--out", str(out)]) == 0
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    assert [a["frames_used"] for a in answers] == [1, 2, 3]
    (stream,) = {a["stream_id"] for a in answers}  # one stream: the sequence's name and this run's id
    assert re.fullmatch(r"city_7_0-[0-9a-f]{6}", stream)
    assert all(a["pose_source"] == "request" for a in answers)
    np.testing.assert_allclose([[a["pose"][k] for k in ("x", "y", "yaw")] for a in answers], POSES, atol=1e-9)
    drawn = cv2.imread(str(out / "frames" / "000003.png"))
    assert drawn.shape == (768, 768 + 300, 3)  # what was covered (the whole scan) fitted to 768 px, beside the panel
    covered = answers[2]["input"]["covered"]
    offset, zoom = covered["offset_px"], 768 / covered["side_px"]
    polygon = (np.asarray(answers[2]["boxes"][0]["polygon"]) - offset) * zoom  # [4, 2] in the zoomed view
    assert red_pixels_along(drawn, polygon) > 0.8  # the best box is outlined in the prediction colour
    video = cv2.VideoCapture(str(out / "sequence.mp4"))
    assert video.isOpened() and int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 3
    captured = capsys.readouterr()
    out_text = captured.out
    assert f"stream {stream}: 3 frames answered" in out_text and "answers.jsonl" in out_text
    assert "frame 000003" not in out_text  # no line per frame: a progress bar on stderr instead


def test_client_without_poses_lets_the_service_use_odometry(sequence, service_url, tmp_path):
    out = tmp_path / "odo"
    assert (
        main(
            [str(sequence), "--url", service_url, "--no-pose", "--limit", "2", "--stream-id", "odo", "--out", str(out)]
        )
        == 0
    )
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    assert [a["pose_source"] for a in answers] == ["odometry", "odometry"]
    assert [a["stream_id"] for a in answers] == ["odo", "odo"]
    assert answers[1]["pose"] != answers[0]["pose"]  # the (fake) odometry moved the ego frame


def test_client_reports_bad_folders_and_unreachable_services(tmp_path, sequence, capsys):
    assert main([str(tmp_path / "nowhere"), "--url", "http://127.0.0.1:9"]) == 2
    assert "Navtech_Cartesian.txt" in capsys.readouterr().err
    assert main([str(sequence), "--url", "http://127.0.0.1:9", "--timeout", "2"]) == 1
    assert "cannot reach" in capsys.readouterr().err


def test_client_on_the_real_radiate_sample(radiate_sample, service_url, tmp_path):
    out = tmp_path / "real"
    assert main([str(radiate_sample), "--url", service_url, "--out", str(out), "--limit", "3", "--no-pose"]) == 0
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    assert [a["input"]["posted_size"] for a in answers] == [1152] * 3
    assert answers[0]["pose"] == {"x": 0.0, "y": 0.0, "yaw": 0.0}


def test_client_on_a_simulated_sequence_sends_its_ego_poses(service_url, tmp_path):
    from rafd.sim import simulate_sequence

    sequence = simulate_sequence(tmp_path / "sim_seq", seed=4, num_frames=3, size=128)
    out = tmp_path / "sim_out"
    assert main([str(sequence), "--url", service_url, "--out", str(out)]) == 0
    answers = [json.loads(line) for line in (out / "answers.jsonl").read_text().splitlines()]
    rows = (sequence / "ego_poses.csv").read_text().splitlines()[1:]
    poses = np.array([[float(v) for v in row.split(",")[2:5]] for row in rows])
    np.testing.assert_allclose([[a["pose"][k] for k in ("x", "y", "yaw")] for a in answers], poses, atol=1e-6)
    assert [a["input"]["posted_size"] for a in answers] == [128] * 3
    assert len(list((out / "frames").glob("*.png"))) == 3


def test_client_sends_its_api_key_to_a_keyed_service(sequence, tmp_path, capsys, monkeypatch):
    import httpx

    from service.app import create_app
    from service.settings import Settings
    from tests.utils.fake_runner import FakeRunner
    from tests.utils.service_testing import FakeOdometry, serve_in_thread, wait_ready

    key = "client-test-key-0123456789"
    settings = Settings(threads=1, api_keys=[f"fleet:{key}"])
    with serve_in_thread(create_app(settings, runner=FakeRunner(), odometry=FakeOdometry())) as url:
        with httpx.Client(base_url=url) as http:
            wait_ready(http)
        monkeypatch.delenv("RAFD_API_KEY", raising=False)
        assert main([str(sequence), "--url", url, "--limit", "1"]) != 0  # no key: refused, said plainly
        assert "HTTP 401" in capsys.readouterr().err
        assert main([str(sequence), "--url", url, "--limit", "2", "--api-key", key, "--out", str(tmp_path / "a")]) == 0
        assert len((tmp_path / "a" / "answers.jsonl").read_text().splitlines()) == 2
        monkeypatch.setenv("RAFD_API_KEY", key)  # the environment's key when --api-key is not given
        assert (
            main([str(sequence), "--url", url, "--limit", "1", "--stream-id", "again", "--out", str(tmp_path / "b")])
            == 0
        )


def test_running_the_same_sequence_again_starts_a_new_stream(sequence, service_url, capsys):
    assert main([str(sequence), "--url", service_url, "--quiet"]) == 0
    assert main([str(sequence), "--url", service_url, "--quiet"]) == 0  # the same timestamps again: a new stream
    out = capsys.readouterr().out
    streams = re.findall(r"stream (city_7_0-[0-9a-f]{6}): 3 frames answered", out)
    assert len(streams) == 2 and streams[0] != streams[1]


def test_a_chosen_stream_repeats_with_reset_and_a_409_names_both_ways_out(sequence, service_url, capsys):
    argv = [str(sequence), "--url", service_url, "--stream-id", "run-a", "--quiet"]
    assert main(argv) == 0
    capsys.readouterr()
    assert main(argv) == 1  # the service holds later timestamps of run-a
    err = capsys.readouterr().err
    assert "HTTP 409" in err and "'run-a'" in err
    assert "DELETE /streams/run-a" in err  # the service's own message names the stream and the ways out
    assert "--reset" in err and "leave out --stream-id" in err  # and so does the client
    assert main([*argv, "--reset"]) == 0
    out = capsys.readouterr().out
    assert "stream run-a: deleted on the service (--reset)" in out and "stream run-a: 3 frames answered" in out
    assert main([str(sequence), "--url", service_url, "--stream-id", "never-seen", "--reset", "--quiet"]) == 0
    assert "stream never-seen: not on the service (--reset)" in capsys.readouterr().out


def test_the_stream_id_travels_in_the_x_stream_id_header_that_routers_hash_on(monkeypatch):
    """Behind deploy/nginx.conf or the Kubernetes ingress a stream stays on one replica only if every request of
    it, the --reset DELETE included, names the stream in X-Stream-Id."""
    import io
    from types import SimpleNamespace

    from rafd.cli import client

    sent = []

    def urlopen(request, timeout):
        sent.append(request)
        return io.BytesIO(b"{}")

    monkeypatch.setattr(client.urllib.request, "urlopen", urlopen)
    frame = SimpleNamespace(timestamp=1.0, pose=None, number=1)
    client.post_frame("http://router", "lane-7", frame, b"png", use_pose=False, timeout=1.0, api_key="k")
    client.reset_stream("http://router", "lane-7", timeout=1.0)
    assert [r.get_method() for r in sent] == ["POST", "DELETE"]
    assert [r.get_header("X-stream-id") for r in sent] == ["lane-7", "lane-7"]
    assert json.loads(sent[0].data)["stream_id"] == "lane-7" and sent[0].get_header("X-api-key") == "k"


def test_a_lost_answer_is_posted_again_with_backoff_and_the_previous_frame_named(monkeypatch):
    """Issue 39: 502 / 503 / 504 and a broken connection are retried with bounded exponential backoff, logged; other
    errors are not; every retry carries the same frame and the previous answered frame's timestamp."""
    import email.message
    import io
    import urllib.error
    from types import SimpleNamespace

    from rafd.cli import client

    def http_error(status: int, retry_after: str | None = None) -> urllib.error.HTTPError:
        headers = email.message.Message()
        if retry_after is not None:
            headers["Retry-After"] = retry_after
        body = io.BytesIO(json.dumps({"error": {"code": "upstream_failed", "message": "x"}}).encode())
        return urllib.error.HTTPError("http://router/detect", status, "Bad Gateway", headers, body)

    failures = [http_error(502), ConnectionResetError("reset by peer"), http_error(503, retry_after="3")]
    sent = []

    def urlopen(request, timeout):
        sent.append(json.loads(request.data))
        if failures:
            raise failures.pop(0)
        return io.BytesIO(b'{"frames_used": 1}')

    monkeypatch.setattr(client.urllib.request, "urlopen", urlopen)
    frame = SimpleNamespace(timestamp=2.0, pose=None, number=7)
    lines, sleeps = [], []
    answer, used = client.post_with_retries(
        4,
        lambda: client.post_frame("http://router", "s", frame, b"png", False, 1.0, None, previous_timestamp=1.75),
        "frame 7",
        log=lines.append,
        sleep=sleeps.append,
    )
    assert answer == {"frames_used": 1} and used == 3
    assert sleeps == [0.25, 0.5, 3.0]  # doubling; Retry-After (3 s) when longer
    assert len(lines) == 3 and "HTTP 502" in lines[0] and "retry 1 of 4" in lines[0] and "retry 3 of 4" in lines[2]
    assert all(body == sent[0] for body in sent) and sent[0]["previous_timestamp"] == 1.75

    # bounded: the last error once the retries are spent; a 4xx is never retried
    failures[:] = [http_error(504)] * 3
    with pytest.raises(client.ServiceError, match="after 2 retries"):
        client.post_with_retries(
            2,
            lambda: client.post_frame("http://r", "s", frame, b"", False, 1.0),
            "f",
            log=lines.append,
            sleep=sleeps.append,
        )
    failures[:] = [http_error(409)]
    calls = len(sent)
    with pytest.raises(client.ServiceError) as refused:
        client.post_with_retries(
            4,
            lambda: client.post_frame("http://r", "s", frame, b"", False, 1.0),
            "f",
            log=lines.append,
            sleep=sleeps.append,
        )
    assert not isinstance(refused.value, client.RetryableError) and len(sent) == calls + 1
    assert client.retry_delay(10) == client.RETRY_MAX_S and client.retry_delay(1, 60.0) == client.RETRY_MAX_S
