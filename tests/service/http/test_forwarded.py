"""Forwarded client addresses trusted only from the proxy (issue 40, finding 3). With FORWARDED_ALLOW_IPS="*" a client
that reached a replica directly rotated X-Forwarded-For and escaped the per-client limit (0 of 24 held requests
refused) and the refusal penalty. With the shipped compose setting (nginx's address only) the header of any other
peer is ignored; behind a proxy that appends, the client is the rightmost entry not from a trusted proxy. Run on the
server rafd-serve runs (uvicorn's proxy headers, service/http/server.py), on loopback."""

from __future__ import annotations

import collections
import contextlib
import socket
from pathlib import Path

import httpx
import pytest
import yaml

from service.app import create_app
from service.http.intake import IntakeMiddleware
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import http_request, read_http_response, serve_in_thread, wait_ready, wait_until

pytestmark = pytest.mark.network

COMPOSE = Path(__file__).resolve().parents[3] / "deploy" / "compose.yaml"


def shipped_trust() -> str:
    return str(yaml.safe_load(COMPOSE.read_text())["x-replica"]["environment"]["FORWARDED_ALLOW_IPS"])


@contextlib.contextmanager
def served(monkeypatch, trusted: str, **overrides):
    """A real server trusting X-Forwarded-For from `trusted`; yields (port, app, the clients the penalty counted)."""
    monkeypatch.setenv("FORWARDED_ALLOW_IPS", trusted)  # read by uvicorn.Config, as in the containers
    app = create_app(Settings(threads=1, **overrides), runner=FakeRunner())
    counted: collections.Counter = collections.Counter()
    penalty = app.state.refusal_penalty
    record = penalty.record
    penalty.record = lambda client: counted.update([client]) or record(client)
    with serve_in_thread(app) as url, httpx.Client(base_url=url, timeout=20.0) as http:
        wait_ready(http)
        yield int(url.rsplit(":", 1)[1]), app, counted


def intake_of(app) -> IntakeMiddleware:
    """The app's IntakeMiddleware (its per-client count of unfinished requests), found in the built middleware stack."""
    layer = app.middleware_stack
    for _ in range(32):  # bounded: a handful of middleware layers
        if isinstance(layer, IntakeMiddleware):
            return layer
        layer = getattr(layer, "app", None)
    raise AssertionError("no IntakeMiddleware in the app's middleware stack")


def hold(port: int, forwarded: str) -> socket.socket:
    """A /detect request whose body never comes (it stays unfinished), sent with the given X-Forwarded-For."""
    head, _ = http_request(
        "POST", "/detect", headers={"Content-Type": "application/json", "X-Forwarded-For": forwarded}
    )
    head = head.replace(b"Content-Length: 0", b"Content-Length: 1000")
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(head)
    return sock


def refused_status(port: int, forwarded: str) -> int:
    head, body = http_request(
        "POST", "/detect", b"{}", {"Content-Type": "application/json", "X-Forwarded-For": forwarded}
    )
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(head + body)
        return read_http_response(sock)[0]


def test_the_shipped_setting_names_the_proxy_not_everyone():
    assert shipped_trust() != "*" and "127.0.0.1" not in shipped_trust()


def test_a_client_rotating_forwarded_addresses_at_a_replica_is_still_limited(monkeypatch):
    """Directly at a replica (loopback is not the trusted proxy): 6 held requests, each with another made-up
    X-Forwarded-For, hold the client's 4 places; the next ones get 429, and every refusal is counted against the
    client's real address, none against a made-up one."""
    # the body-rate check off: on a loaded machine a held body would be refused as too slow after its 1 s grace,
    # freeing a place before the six refusals are sent
    settings = {"max_requests_per_client": 4, "body_timeout_s": 20.0, "min_body_bytes_per_s": 0}
    with served(monkeypatch, shipped_trust(), **settings) as (port, app, counted):
        intake = intake_of(app)
        held = [hold(port, f"203.0.113.{k}") for k in range(4)]
        try:
            wait_until(lambda: sum(intake.unfinished.values()) == 4, message="four requests unfinished")
            assert set(intake.unfinished) == {"127.0.0.1"}  # one client, whatever its headers say
            statuses = [refused_status(port, f"198.51.100.{k}") for k in range(6)]
        finally:
            for sock in held:
                sock.close()
    assert statuses == [429] * 6, statuses
    assert set(counted) == {"127.0.0.1"} and counted["127.0.0.1"] >= 6


def test_refusals_with_rotating_forwarded_addresses_are_penalised_as_one_client(monkeypatch):
    """Invalid bodies sent with a new X-Forwarded-For each: all counted for the one real client, so the penalty
    (more than 3 refusals a second) applies to it; before, each made-up address got its own allowance."""
    with served(monkeypatch, shipped_trust()) as (port, _, counted):
        statuses = [refused_status(port, f"192.0.2.{k}") for k in range(5)]
    assert statuses == [422] * 5
    assert dict(counted) == {"127.0.0.1": 5}


def test_behind_an_appending_proxy_the_client_is_the_rightmost_untrusted_entry(monkeypatch):
    """The proxy (here loopback, trusted) appends the address it saw; entries the client wrote itself come first and
    are ignored: every refusal counts against the address the proxy appended."""
    with served(monkeypatch, "127.0.0.1") as (port, _, counted):
        statuses = [refused_status(port, f"192.0.2.{k}, 198.51.100.7") for k in range(4)]
    assert statuses == [422] * 4
    assert dict(counted) == {"198.51.100.7": 4}
