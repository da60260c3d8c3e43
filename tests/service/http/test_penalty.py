"""A client that keeps sending refused images gets its refusals slowly; valid requests and other clients never."""

from __future__ import annotations

from fastapi.testclient import TestClient

import service.http.errors
from service.app import create_app
from service.http.penalty import MAX_CLIENTS, RefusalPenalty
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import detect_json, wait_ready

FRAME_SIZE = 128


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_delay_only_beyond_the_allowance_within_a_second_and_per_client() -> None:
    clock = Clock()
    penalty = RefusalPenalty(0.5, after=3, clock=clock)
    assert [penalty.record("a") for _ in range(5)] == [0.0, 0.0, 0.0, 0.5, 0.5]
    assert penalty.record("b") == 0.0  # another client is not penalised for a's refusals
    clock.now += 1.5  # the window has passed: a starts afresh
    assert penalty.record("a") == 0.0
    assert RefusalPenalty(0.0, after=0, clock=clock).record("a") == 0.0  # 0 s turns it off


def test_remembered_clients_are_bounded() -> None:
    penalty = RefusalPenalty(0.5, after=3, clock=Clock())
    for k in range(MAX_CLIENTS + 10):
        penalty.record(f"client-{k}")
    assert len(penalty._recent) == MAX_CLIENTS


def test_the_service_delays_repeated_refusals_not_valid_frames(monkeypatch) -> None:
    import numpy as np

    slept: list[float] = []

    async def fake_sleep(seconds: float) -> None:
        slept.append(seconds)

    monkeypatch.setattr(service.http.errors.asyncio, "sleep", fake_sleep)
    settings = Settings(threads=1, refusal_penalty_s=0.25, refusal_penalty_after=2)
    frame = np.zeros((FRAME_SIZE, FRAME_SIZE), np.uint8)
    with TestClient(create_app(settings, runner=FakeRunner())) as client:
        wait_ready(client)
        for t in range(4):
            bad = detect_json("flood", float(t), frame) | {"image": "bm90IGEgcG5n"}  # base64 of "not a png"
            response = client.post("/detect", json=bad)
            assert response.status_code == 422 and response.json()["error"]["code"] == "invalid_image"
        for t in range(3):  # valid frames of the same address are answered without delay
            assert client.post("/detect", json=detect_json("normal", float(t), frame, (0, 0, 0))).status_code == 200
    assert slept == [0.25, 0.25]  # the 3rd and 4th refusal within the second
