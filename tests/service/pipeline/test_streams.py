"""The per-stream store: TTL expiry and LRU cap (with an injected clock), delete/reset, GET /streams."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from fastapi.testclient import TestClient

from rafd.runtime.view import View
from service.app import create_app
from service.pipeline.poses import OdometryMemory
from service.pipeline.streams import Chain, StreamStore
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import blob_frame, detect_json, wait_ready

FRAME = blob_frame(128, [(8, 8, 255)])
VIEW = View.of(128, 128, 0.173611, 4)


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def make_store(max_streams=3, ttl_s=10.0):
    clock, evicted = Clock(), []
    store = StreamStore(max_streams, ttl_s, clock=clock, on_evict=evicted.append)
    return store, clock, evicted


def _advanced(chain: Chain, timestamp: float) -> Chain:
    memory = OdometryMemory(FRAME, timestamp)
    return chain.advanced(chain.model, memory, np.zeros(3), "request", timestamp, VIEW, chain.tracks)


async def feed(store: StreamStore, stream_id: str, timestamp: float) -> None:
    """What a successful detect does to the store: take a ticket, wait for the turn, commit, release."""
    ticket = store.take_ticket(stream_id)
    try:
        store.place(ticket, timestamp)
        await store.wait_turn(ticket)
        store.commit(ticket, _advanced(ticket.entry.chain, timestamp))
    finally:
        store.release(ticket)


async def hold(store: StreamStore, stream_id: str, timestamp: float):
    """A frame that committed and whose request has not ended yet (the caller releases the ticket)."""
    ticket = store.take_ticket(stream_id)
    store.place(ticket, timestamp)
    await store.wait_turn(ticket)
    store.commit(ticket, _advanced(ticket.entry.chain, timestamp))
    return ticket


def test_store_expires_idle_streams_after_the_ttl():
    store, clock, evicted = make_store(ttl_s=10.0)
    asyncio.run(feed(store, "a", 1.0))
    clock.now += 5.0
    asyncio.run(feed(store, "b", 1.0))
    clock.now += 6.0  # a idle 11 s, b idle 6 s
    assert [s.stream_id for s in store.snapshot()] == ["b"]
    assert evicted == ["ttl"]
    assert "a" not in store and len(store) == 1
    assert store.snapshot()[0].idle_s == pytest.approx(6.0)
    clock.now += 4.5  # b idle 10.5 s
    assert len(store) == 0 and evicted == ["ttl", "ttl"]


def test_store_evicts_the_least_recently_used_at_the_cap():
    store, clock, evicted = make_store(max_streams=3)
    for name in ("a", "b", "c"):
        asyncio.run(feed(store, name, 1.0))
        clock.now += 1.0
    asyncio.run(feed(store, "a", 2.0))  # a is now the most recent; b the least
    asyncio.run(feed(store, "d", 1.0))
    assert sorted(s.stream_id for s in store.snapshot()) == ["a", "c", "d"]
    assert evicted == ["lru"]


def test_store_never_evicts_a_stream_with_a_request_in_flight():
    async def scenario(store: StreamStore) -> list[str]:
        busy = await hold(store, "busy", 1.0)
        await feed(store, "x", 1.0)  # cap 2 reached: busy + x
        await feed(store, "y", 1.0)  # must evict x (idle), not busy
        names = sorted(s.stream_id for s in store.snapshot())
        store.release(busy)
        return names

    store, _, evicted = make_store(max_streams=2)
    assert asyncio.run(scenario(store)) == ["busy", "y"]
    assert evicted == ["lru"]


def test_cap_waits_for_in_flight_streams_then_applies():
    async def scenario(store: StreamStore) -> list[str]:
        busy = await hold(store, "busy", 1.0)
        await feed(store, "other", 1.0)  # cap 1, but "busy" is in flight: nothing can go yet
        assert sorted(s.stream_id for s in store.snapshot()) == ["busy", "other"]
        store.release(busy)
        return [s.stream_id for s in store.snapshot()]

    store, _, evicted = make_store(max_streams=1)
    assert asyncio.run(scenario(store)) == ["busy"]  # "other" was the least recently used once busy ended
    assert evicted == ["lru"]


def test_a_new_stream_whose_first_frame_fails_leaves_nothing():
    async def failing(store: StreamStore) -> None:
        ticket = store.take_ticket("new")
        try:
            store.place(ticket, 1.0)
            await store.wait_turn(ticket)
            raise RuntimeError("model failed")
        finally:
            store.release(ticket)

    store, _, evicted = make_store(max_streams=1)
    asyncio.run(feed(store, "old", 1.0))
    with pytest.raises(RuntimeError):
        asyncio.run(failing(store))
    assert store.get("new") is None and "new" not in store._entries
    assert [s.stream_id for s in store.snapshot()] == ["old"] and evicted == []  # the failure evicted nobody


@pytest.fixture
def clocked():
    clock = Clock()
    settings = Settings(threads=1, max_streams=3, stream_ttl_s=60.0)
    with TestClient(create_app(settings, runner=FakeRunner(), clock=clock)) as client:
        wait_ready(client)
        yield client, clock


def test_endpoints_list_streams_and_count_ttl_and_lru_evictions(clocked):
    client, clock = clocked
    for name in ["a", "b", "c", "d"]:  # d evicts a (LRU)
        assert client.post("/detect", json=detect_json(name, 1.0, FRAME, (0, 0, 0))).status_code == 200
        clock.now += 10.0
    body = client.get("/streams").json()
    assert body["count"] == 3 and body["max_streams"] == 3 and body["ttl_s"] == 60.0
    rows = {s["stream_id"]: s for s in body["streams"]}
    assert set(rows) == {"b", "c", "d"}
    assert rows["b"]["idle_s"] == pytest.approx(30.0) and rows["d"]["idle_s"] == pytest.approx(10.0)
    assert rows["d"]["frames_buffered"] == 1 and rows["d"]["last_timestamp"] == 1.0
    clock.now += 45.0  # b (75 s) and c (65 s) idle past the TTL, d at 55 s
    assert [s["stream_id"] for s in client.get("/streams").json()["streams"]] == ["d"]
    metrics = client.get("/metrics").text
    assert 'rafd_stream_evictions_total{reason="lru"} 1.0' in metrics
    assert 'rafd_stream_evictions_total{reason="ttl"} 2.0' in metrics
    assert "rafd_active_streams 1.0" in metrics
    # An expired stream starts over: an old timestamp is accepted again and the buffer restarts.
    again = client.post("/detect", json=detect_json("b", 0.5, FRAME, (0, 0, 0))).json()
    assert again["frames_used"] == 1


def test_delete_resets_a_stream(clocked):
    client, _ = clocked
    for t in (1.0, 2.0, 3.0):
        client.post("/detect", json=detect_json("r", t, FRAME, (t, 0, 0)))
    assert client.delete("/streams/r").status_code == 204
    assert client.get("/streams").json()["count"] == 0
    assert client.delete("/streams/r").status_code == 404
    restarted = client.post("/detect", json=detect_json("r", 1.0, FRAME, (0, 0, 0))).json()
    assert restarted["frames_used"] == 1 and restarted["warming_up"] is True


def test_a_stream_queues_at_most_its_limit_and_a_refused_ticket_changes_nothing():
    from service.http.errors import ApiError

    store, clock, _ = make_store()
    store.queue_limit = 2
    asyncio.run(feed(store, "q", 1.0))
    before = store.snapshot()
    first, second = store.take_ticket("q"), store.take_ticket("q")
    clock.now += 5.0
    with pytest.raises(ApiError) as refused:
        store.take_ticket("q")
    assert refused.value.status == 429 and refused.value.headers == {"Retry-After": "1"}
    assert [t for t in store.get("q").queue] == [first, second]
    store.release(first)
    store.release(second)
    assert store.snapshot()[0].idle_s == pytest.approx(before[0].idle_s + 5.0)  # no idle refresh either


def test_generation_increases_per_chain_and_a_closed_chain_refuses_its_tickets():
    from service.http.errors import ApiError

    async def scenario(store: StreamStore) -> None:
        await feed(store, "g", 1.0)
        waiting = store.take_ticket("g")
        assert store.delete("g")
        with pytest.raises(ApiError) as reset:
            store.place(waiting, 2.0)
            await store.wait_turn(waiting)
        assert reset.value.code == "stream_reset"
        store.release(waiting)
        await feed(store, "g", 0.5)  # a new chain: an older timestamp is fine

    store, _, _ = make_store()
    asyncio.run(scenario(store))
    (info,) = store.snapshot()
    assert info.generation == 2 and info.frames_seen == 1 and info.last_timestamp == 0.5
