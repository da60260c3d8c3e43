"""Optional API keys: required everywhere but liveness/readiness when configured; streams belong to their key."""

from __future__ import annotations

import hmac

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.cli import main as serve_main
from service.http import auth
from service.http.auth import ApiKeys, load_api_keys, parse_key
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import blob_frame, detect_json, wait_ready

FRAME = blob_frame(128, [(8, 8, 255)])
ALICE, BOB = "alice-key-0123456789abcdef", "bob-key-0123456789abcdef01"
A = {"X-API-Key": ALICE}
B = {"Authorization": f"Bearer {BOB}"}


@pytest.fixture
def keyed(tmp_path) -> TestClient:
    keys_file = tmp_path / "keys"
    keys_file.write_text(f"# fleet keys\n\nbob:{BOB}\n")
    settings = Settings(threads=1, api_keys=[f"alice:{ALICE}"], api_keys_file=keys_file)
    with TestClient(create_app(settings, runner=FakeRunner())) as client:
        wait_ready(client)
        yield client


def test_without_keys_configured_everything_is_open(client):
    assert client.get("/streams").status_code == 200 and client.get("/metrics").status_code == 200
    assert "securitySchemes" not in client.get("/openapi.json").json().get("components", {})


@pytest.mark.parametrize(
    "method,path",
    [
        ("POST", "/detect"),
        ("POST", "/streams/x/detect"),
        ("GET", "/streams"),
        ("DELETE", "/streams/x"),
        ("GET", "/model"),
        ("GET", "/metrics"),
        ("GET", "/openapi.json"),
        ("GET", "/docs"),
        ("GET", "/nope"),
    ],
)
def test_every_route_but_the_probes_needs_a_valid_key(keyed, method, path):
    for headers, code in (
        ({}, "missing_api_key"),
        ({"X-API-Key": "wrong-key-0123456789abcdef"}, "invalid_api_key"),
        ({"Authorization": "Bearer wrong-key-0123456789abcdef"}, "invalid_api_key"),
        ({"Authorization": f"Basic {ALICE}"}, "missing_api_key"),  # not a scheme the service reads keys from
        ({"Authorization": "Bearer "}, "missing_api_key"),
    ):
        response = keyed.request(method, path, headers=headers, json=detect_json("x", 1.0, FRAME))
        assert response.status_code == 401, (headers, response.text)
        assert response.json()["error"]["code"] == code, headers
        assert response.headers["www-authenticate"].startswith("Bearer")
    assert keyed.request(method, path, headers=A, json=detect_json("x", 1.0, FRAME)).status_code != 401


def test_liveness_and_readiness_need_no_key(keyed):
    assert keyed.get("/health/live").status_code == 200
    assert keyed.get("/health/ready").status_code == 200


def test_each_key_has_its_own_stream_namespace_with_no_existence_oracle(keyed):
    """Issue 34 finding 7: stream ids were one namespace across keys, so key B could tell whether A's id existed (403
    vs 404 on DELETE) and squat an id first (A then got 403 until the TTL). Now A's `car` and B's `car` are two
    streams: B sees nothing of A's, and posting first takes nothing from A."""
    # B posts first
    assert keyed.post("/detect", json=detect_json("car", 1.0, FRAME, (0, 0, 0)), headers=B).status_code == 200
    assert keyed.post("/detect", json=detect_json("car", 5.0, FRAME, (0, 0, 0)), headers=A).status_code == 200
    assert keyed.post("/detect", json=detect_json("car", 2.0, FRAME, (0, 0, 0)), headers=B).json()["frames_used"] == 2
    # no oracle: B's DELETE of an id only A has is the same 404 as of an id nobody has
    assert keyed.post("/detect", json=detect_json("only-a", 1.0, FRAME, (0, 0, 0)), headers=A).status_code == 200
    only_a, nobody = keyed.delete("/streams/only-a", headers=B), keyed.delete("/streams/nobody", headers=B)
    assert only_a.status_code == nobody.status_code == 404
    assert only_a.json()["error"]["code"] == nobody.json()["error"]["code"] == "stream_not_found"
    listed = {name: keyed.get("/streams", headers=headers).json()["streams"] for name, headers in (("a", A), ("b", B))}
    assert sorted(s["stream_id"] for s in listed["a"]) == ["car", "only-a"]
    assert [s["stream_id"] for s in listed["b"]] == ["car"]
    assert {s["stream_id"]: s["last_timestamp"] for s in listed["a"]}["car"] == 5.0  # B changed nothing of A's
    assert listed["b"][0]["last_timestamp"] == 2.0 and listed["b"][0]["frames_seen"] == 2
    # B resets its own car; A's goes on
    assert keyed.delete("/streams/car", headers=B).status_code == 204
    assert keyed.post("/detect", json=detect_json("car", 6.0, FRAME, (0, 0, 0)), headers=A).json()["frames_used"] == 2


def test_refusals_are_counted_in_the_metrics_under_the_route(keyed):
    keyed.get("/streams")
    keyed.get("/no/such/route")
    metrics = keyed.get("/metrics", headers=A).text
    assert 'rafd_requests_total{code="401",method="GET",route="/streams"} 1.0' in metrics
    assert 'rafd_requests_total{code="401",method="GET",route="unmatched"} 1.0' in metrics


def test_openapi_documents_the_key_schemes_and_the_open_probes(keyed):
    spec = keyed.get("/openapi.json", headers=A).json()
    assert set(spec["components"]["securitySchemes"]) == {"ApiKeyHeader", "BearerAuth"}
    assert spec["paths"]["/health/ready"]["get"]["security"] == []
    assert {"ApiKeyHeader": []} in spec["paths"]["/detect"]["post"]["security"]
    assert "401" in spec["paths"]["/detect"]["post"]["responses"]


def test_keys_are_compared_in_constant_time_with_no_early_exit(monkeypatch):
    keys = ApiKeys(tuple((f"k{i}", auth._digest(f"key-number-{i:02d}-abcdefgh")) for i in range(5)))
    calls = []
    monkeypatch.setattr(hmac, "compare_digest", lambda a, b: calls.append((len(a), len(b))) or a == b)
    assert keys.identify("key-number-00-abcdefgh") == "k0"
    assert calls == [(32, 32)] * 5  # every key compared, digests of equal length, even after the match
    calls.clear()
    assert keys.identify("unknown-key-0123456789") is None and len(calls) == 5


def test_key_parsing_and_loading_errors(tmp_path):
    assert parse_key(f"fleet:{ALICE}", "x") == ("fleet", ALICE)
    name, key = parse_key(ALICE, "x")
    assert key == ALICE and name.startswith("key-") and ALICE not in name
    for bad in ("short", f"bad name:{ALICE}", "k" * 300, f"{ALICE} trailing"):
        with pytest.raises(ValueError):
            parse_key(bad, "x")
    with pytest.raises(ValueError, match="unique"):
        load_api_keys(Settings(threads=1, api_keys=[f"a:{ALICE}", f"b:{ALICE}"]))
    with pytest.raises(ValueError, match="cannot be read"):
        load_api_keys(Settings(threads=1, api_keys_file=tmp_path / "missing"))
    bad_file = tmp_path / "keys"
    bad_file.write_text("ok-key-0123456789abcdef\nnot a key\n")
    with pytest.raises(ValueError, match="line 2"):
        load_api_keys(Settings(threads=1, api_keys_file=bad_file))


def test_environment_keys_are_comma_separated(monkeypatch):
    monkeypatch.setenv("RAFD_API_KEYS", f"alice:{ALICE}, {BOB}")
    keys = load_api_keys(Settings(threads=1))
    assert keys.identify(ALICE) == "alice" and keys.identify(BOB).startswith("key-")


def test_rafd_serve_refuses_to_start_with_a_bad_key_file(tmp_path, monkeypatch, capsys):
    import uvicorn

    model = tmp_path / "m.onnx"
    model.write_bytes(b"onnx")
    monkeypatch.setenv("RAFD_API_KEYS_FILE", str(tmp_path / "missing-keys"))
    monkeypatch.setattr(uvicorn, "run", lambda *a, **k: pytest.fail("must not serve"))
    assert serve_main(["--model", str(model)]) == 2
    assert "missing-keys" in capsys.readouterr().err


def test_the_two_401s_say_which_mistake_and_nothing_about_the_keys(keyed):
    missing = keyed.get("/model").json()["error"]
    wrong = keyed.get("/model", headers={"X-API-Key": ALICE[:-1] + "x"}).json()["error"]  # one character off
    assert (missing["code"], wrong["code"]) == ("missing_api_key", "invalid_api_key")
    assert "X-API-Key" in missing["message"] and "not valid" in wrong["message"]
    for message in (missing["message"], wrong["message"]):
        assert ALICE not in message and "alice" not in message and "bob" not in message
        assert ALICE[:8] not in message  # not even a prefix of a configured key
