"""Concurrency: streams stay isolated under interleaved posts; one stream's frames run in timestamp order."""

from __future__ import annotations

import random
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from fastapi.testclient import TestClient

from rafd.detections import decode_detections
from service.app import create_app
from tests.utils.fake_runner import WARM_UP_RUNS, FakeRunner
from tests.utils.service_testing import blob_frame, detect_json, stream_state, wait_ready

STREAMS = 20
FRAMES_PER_STREAM = 5


def stream_frames(k: int) -> tuple[list[np.ndarray], list[tuple[float, float, float]]]:
    """Stream k's own frames: spots at stream-specific places and brightness, moving per frame."""
    rng = np.random.default_rng(k)
    frames, poses = [], []
    for t in range(FRAMES_PER_STREAM):
        spots = [
            (int(r) // 4 * 4, int(c) // 4 * 4, int(v))
            for r, c, v in zip(rng.integers(0, 124, 3), rng.integers(0, 124, 3), rng.integers(90, 256, 3))
        ]
        frames.append(blob_frame(128, spots))
        poses.append((float(k), float(t), 0.01 * k * t))
    return frames, poses


def test_twenty_concurrent_streams_stay_isolated(settings):
    settings.concurrent_runs = 2  # two steps at once, so different streams really run concurrently
    settings.model_queue_limit = STREAMS  # every stream's frame may wait: this test is not about overload
    settings.parse_queue_limit = STREAMS
    settings.max_requests_per_client = STREAMS  # one test client posts all the streams
    runner = FakeRunner(delay_s=0.003)
    data = {k: stream_frames(k) for k in range(STREAMS)}

    def post_stream(client: TestClient, k: int) -> list[dict]:
        frames, poses = data[k]
        answers = []
        for t in range(FRAMES_PER_STREAM):
            response = client.post("/detect", json=detect_json(f"veh-{k}", 1000.0 + t, frames[t], poses[t]))
            assert response.status_code == 200, response.text
            answers.append(response.json())
        return answers

    with TestClient(create_app(settings, runner=runner)) as client:
        wait_ready(client)
        with ThreadPoolExecutor(max_workers=STREAMS) as pool:
            results = dict(zip(range(STREAMS), pool.map(lambda k: post_stream(client, k), range(STREAMS))))
        assert client.get("/streams").json()["count"] == STREAMS
        assert all(stream_state(client, f"veh-{k}")["frames_seen"] == FRAMES_PER_STREAM for k in range(STREAMS))
    assert runner.max_in_flight > 1  # the streams really ran concurrently

    for k, answers in results.items():
        offline, state = FakeRunner(), None
        state = offline.new_state()
        frames, poses = data[k]
        for t, answer in enumerate(answers):
            frame = (frames[t].astype(np.float32) / 255.0)[None]
            result, state = offline.step(state, frame, np.asarray(poses[t])[None])
            result = result.view(0)
            expected = decode_detections(result.boxes, result.scores, settings.score_threshold)
            got = np.array([[b["x"], b["y"], b["width"], b["length"], b["yaw"], b["score"]] for b in answer["boxes"]])
            np.testing.assert_allclose(got, expected.as_array(), atol=1e-4, err_msg=f"stream {k} frame {t}")
            assert answer["frames_used"] == result.frames_used
            if t:
                np.testing.assert_allclose(answer["flow"]["values"], result.flow, atol=5e-4)


def test_concurrent_posts_to_one_stream_are_processed_in_timestamp_order(settings):
    count = 30
    order = list(range(1, count + 1))
    random.Random(3).shuffle(order)
    runner = FakeRunner(delay_s=0.002)

    def post(i: int):
        frame = np.full(
            (128, 128), 8 * i, np.uint8
        )  # frame i is uniform 8 * i: the fake's flow reveals its predecessor
        return i, client.post("/detect", json=detect_json("one", float(i), frame, (float(i), 0.0, 0.0)))

    # Refused frames leave gaps of whole seconds between accepted ones: not a radar's timing, so the staleness rule
    # (RAFD_STREAM_GAP_RESTART_S, tests/service/pipeline/test_chain_restart.py) is off here.
    settings = settings.model_copy(update={"stream_gap_restart_s": 0.0})
    with TestClient(create_app(settings, runner=runner)) as client:
        wait_ready(client)
        with ThreadPoolExecutor(max_workers=8) as pool:
            responses = dict(pool.map(post, order))
        final = stream_state(client, "one")

    assert {r.status_code for r in responses.values()} <= {200, 409}
    accepted = sorted(i for i, r in responses.items() if r.status_code == 200)
    assert accepted and accepted[-1] == count  # the newest frame can never be refused
    for rank, i in enumerate(accepted):
        answer = responses[i].json()
        assert answer["frames_used"] == min(rank + 1, 4)
        if rank == 0:
            assert answer["flow"] is None
        else:
            predecessor = i - answer["flow"]["values"][0][0][0] / 8.0  # flow x = 255 * (new - previous) / 255
            assert round(predecessor) == accepted[rank - 1], f"frame {i} was stepped after {predecessor}"
            assert answer["flow"]["pair"] == [float(accepted[rank - 1]), float(i)]
    for response in responses.values():
        if response.status_code == 409:
            assert response.json()["error"]["code"] == "timestamp_not_increasing"
    assert final["last_timestamp"] == float(count)
    assert final["frames_seen"] == len(accepted)
    assert final["frames_buffered"] == min(len(accepted), 4)
    assert runner.calls == len(accepted) + WARM_UP_RUNS  # refused frames never reached the model
