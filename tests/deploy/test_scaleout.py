"""Sticky scale-out: the shipped nginx.conf (Debian's nginx) in front of 3 rafd-serve replicas on loopback.

Every stream sticks to one replica; the answers equal a single process's; when a replica is killed, only its
streams re-warm (each on one survivor, where it then sticks) while the other streams answer on unchanged.
Real tiny_foggy scans with poses (no odometry: the test is about routing, and stays fast).
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from bench.loopback import LoopbackCluster, nginx_binary
from bench.server import http_get
from rafd import detect_client
from tests.utils.answers_testing import assert_same_answer, in_process_service

pytestmark = pytest.mark.network

if nginx_binary() is None:
    pytest.skip(
        "nginx is not installed (Debian: apt-get install nginx; .ci/run installs it where it may)",
        allow_module_level=True,
    )

REPLICAS = 3
# Pinned on the replicas and the single reference process alike, so their answers are comparable.
PINNED = {"runtime": "onnxruntime", "precision": "fp32", "threads": 1, "concurrent_runs": 1}
STREAMS_PER_REPLICA = 2  # streams are added until every replica holds at least this many
MAX_STREAMS = 60
FRAMES_BEFORE, FRAMES_AFTER = 3, 2  # frames per stream before and after a replica is killed


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LoopbackCluster]:
    env = {f"RAFD_{k.upper()}": str(v) for k, v in PINNED.items()} | {"OMP_NUM_THREADS": "1"}
    with LoopbackCluster(REPLICAS, tmp_path_factory.mktemp("scaleout"), env) as running:
        yield running


@pytest.fixture(scope="module")
def reference() -> Iterator[TestClient]:
    """The single process: the same service in this process, same settings."""
    with in_process_service(**PINNED) as client:
        yield client


def frame_body(scans: list[Path], stream_index: int, t: int) -> dict[str, Any]:
    """Frame t of stream k: scan (k + t) of the sample, driving 2 m forward per frame."""
    path = scans[(stream_index + t) % len(scans)]
    fields = detect_client.FrameFields(100.0 + t, None, (0.0, 2.0 * t, 0.0))
    return fields.json_fields(detect_client.base64_png(path.read_bytes()))


def via_nginx(url: str, stream: str, body: dict[str, Any], path_form: bool) -> tuple[dict[str, Any], str]:
    """POST one frame through nginx naming the stream in the header or in the path: (answer, replica address)."""
    target, headers = f"{url}/detect", {"content-type": "application/json"}
    if path_form:
        target = f"{url}/streams/{stream}/detect"
    else:
        headers["x-stream-id"] = stream
    request = urllib.request.Request(target, data=json.dumps(body).encode(), headers=headers, method="POST")
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            # $upstream_addr: every replica tried, in order ("a, b" after a refused connection); the last answered.
            return json.loads(response.read()), response.headers["X-RaFD-Replica"].split(", ")[-1]
    except urllib.error.HTTPError as exc:
        raise AssertionError(f"{stream}: HTTP {exc.code} {exc.read()[:500]!r}") from exc


def on_reference(client: TestClient, stream: str, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post("/detect", json={**body, "stream_id": stream})
    assert response.status_code == 200, response.text
    return response.json()


def streams_on(cluster: LoopbackCluster, index: int) -> dict[str, int]:
    """{stream id: frames_seen} held by one replica (asked directly, not through nginx)."""
    status, body = http_get(f"http://{cluster.replica_address(index)}/streams")
    assert status == 200
    return {row["stream_id"]: row["frames_seen"] for row in json.loads(body)["streams"]}


def test_streams_stick_answer_as_one_process_and_only_a_killed_replicas_streams_rewarm(
    cluster: LoopbackCluster, reference: TestClient, radiate_sample: Path
):
    scans = sorted((radiate_sample / "Navtech_Cartesian").glob("*.png"))
    num_frames = reference.get("/model").json()["num_frames"]
    replicas = [cluster.replica_address(i) for i in range(REPLICAS)]

    # Frame 0 of new streams until every replica holds a few: where each stream lands is the ring's choice.
    home: dict[str, str] = {}
    while min(sum(r == replica for r in home.values()) for replica in replicas) < STREAMS_PER_REPLICA:
        assert len(home) < MAX_STREAMS, f"{MAX_STREAMS} streams and still a replica with too few: {home}"
        stream = f"car-{len(home):03d}"
        body = frame_body(scans, len(home), 0)
        answer, replica = via_nginx(cluster.url, stream, body, path_form=len(home) % 2 == 1)
        assert_same_answer(answer, on_reference(reference, stream, body))
        home[stream] = replica
    streams = list(home)
    path_form = {s: i % 2 == 1 for i, s in enumerate(streams)}  # both ways of naming the stream

    # Sticky: every later frame of a stream reaches its replica and answers as the single process does.
    for t in range(1, FRAMES_BEFORE):
        for k, stream in enumerate(streams):
            body = frame_body(scans, k, t)
            answer, replica = via_nginx(cluster.url, stream, body, path_form[stream])
            assert replica == home[stream], (stream, t)
            assert answer["frames_used"] == min(t + 1, num_frames)
            assert_same_answer(answer, on_reference(reference, stream, body))
    held = [streams_on(cluster, i) for i in range(REPLICAS)]
    for stream in streams:  # each stream is in exactly one replica's store, with all its frames
        assert [h.get(stream) for h in held].count(FRAMES_BEFORE) == 1 and sum(stream in h for h in held) == 1

    victim = 0
    moved = [s for s in streams if home[s] == replicas[victim]]
    stayed = [s for s in streams if s not in moved]
    cluster.kill(victim)

    new_home: dict[str, str] = {}
    for t in range(FRAMES_BEFORE, FRAMES_BEFORE + FRAMES_AFTER):
        for k, stream in enumerate(streams):
            body = frame_body(scans, k, t)
            answer, replica = via_nginx(cluster.url, stream, body, path_form[stream])
            if stream in stayed:  # answers on, unchanged: same replica, its buffer intact
                assert replica == home[stream], (stream, t)
                assert answer["frames_used"] == min(t + 1, num_frames)
                assert_same_answer(answer, on_reference(reference, stream, body))
            else:  # moved to a survivor, where it re-warms and then sticks
                assert replica != replicas[victim]
                assert new_home.setdefault(stream, replica) == replica, (stream, t)
                assert answer["frames_used"] == t - FRAMES_BEFORE + 1
                assert_same_answer(answer, on_reference(reference, f"{stream}.rewarmed", body))
    survivors = [streams_on(cluster, i) for i in range(REPLICAS) if i != victim]
    for stream in moved:
        assert [h.get(stream) for h in survivors].count(FRAMES_AFTER) == 1
    for stream in stayed:
        assert [h.get(stream) for h in survivors].count(FRAMES_BEFORE + FRAMES_AFTER) == 1
    assert moved and stayed

    # DELETE /streams/{id} is routed on the path too: it reaches the replica that holds the stream.
    for stream in (moved[0], stayed[0]):
        request = urllib.request.Request(f"{cluster.url}/streams/{stream}", method="DELETE")
        with urllib.request.urlopen(request, timeout=10) as response:
            assert response.status == 204
    held = [streams_on(cluster, i) for i in range(REPLICAS) if i != victim]
    assert not any(moved[0] in h or stayed[0] in h for h in held)
