"""Every malformed request gets a 4xx {"error": {"code", "message"}} and changes no stream."""
from __future__ import annotations

import base64
import json

import numpy as np
import pytest
from fake_runner import FakeRunner
from fastapi.testclient import TestClient
from service_testing import b64png, blob_frame, detect_json, png, stream_state, wait_ready

from service.app import create_app
from service.settings import Settings

FRAME = blob_frame(128, [(8, 8, 255)])
GOOD_PNG = png(FRAME)


def body(**changes):
    base = detect_json("s", 10.0, FRAME, (1.0, 2.0, 0.1))
    base.update(changes)
    return {k: v for k, v in base.items() if v is not ...}


def raw_json(text: str) -> dict:
    return {"content": text.encode(), "headers": {"content-type": "application/json"}}


def form(data: dict, image: bytes | None = GOOD_PNG) -> dict:
    """multipart/form-data: plain fields as (None, value) parts, so it stays multipart without a file."""
    fields = {"stream_id": "s", "timestamp": "10.0", **data}
    files = {k: (None, v) for k, v in fields.items()}
    if image is not None:
        files["image"] = ("f.png", image, "image/png")
    return {"files": files}


GOOD_BODY = json.dumps(body())
CASES = {
    "wrong content type": (415, "unsupported_media_type", {"content": GOOD_BODY.encode(), "headers": {"content-type": "text/plain"}}),
    "no content type": (415, "unsupported_media_type", {"content": GOOD_BODY.encode()}),
    "invalid json": (400, "invalid_json", raw_json('{"stream_id": "s", ')),
    "json not an object": (422, "validation_error", raw_json("[1, 2]")),
    "empty body": (400, "empty_body", raw_json("")),
    "missing image": (422, "validation_error", {"json": body(image=...)}),
    "missing timestamp": (422, "validation_error", {"json": body(timestamp=...)}),
    "missing stream id": (422, "validation_error", {"json": body(stream_id=...)}),
    "unknown field": (422, "validation_error", {"json": body(frame=1)}),
    "pose missing yaw": (422, "validation_error", {"json": body(pose={"x": 1.0, "y": 2.0})}),
    "timestamp not a number": (422, "validation_error", {"json": body(timestamp="soon")}),
    "not base64": (422, "invalid_image", {"json": body(image="%%% not base64 %%%")}),
    "base64 not an image": (422, "invalid_image", {"json": body(image=base64.b64encode(b"hello radar").decode())}),
    "empty image": (422, "validation_error", {"json": body(image="")}),
    "truncated png": (422, "invalid_image", {"json": body(image=base64.b64encode(GOOD_PNG[: len(GOOD_PNG) // 2]).decode())}),
    "jpeg not png": (422, "invalid_image", {"json": body(image=base64.b64encode(b"\xff\xd8\xff\xe0" + bytes(64)).decode())}),
    "wrong size": (422, "unsupported_image_size", {"json": body(image=b64png(np.zeros((64, 64), np.uint8)))}),
    "not square": (422, "unsupported_image_size", {"json": body(image=b64png(np.zeros((1152, 1000), np.uint8)))}),
    "colour image": (422, "unsupported_image_format", {"json": body(image=b64png(np.zeros((128, 128, 3), np.uint8)))}),
    "grey + alpha": (422, "unsupported_image_format", {"json": body(image=b64png(np.zeros((128, 128, 4), np.uint8)))}),
    "16-bit image": (422, "unsupported_image_format", {"json": body(image=b64png(np.zeros((128, 128), np.uint16)))}),
    "NaN pose literal": (400, "invalid_json", raw_json(GOOD_BODY.replace('"x": 1.0', '"x": NaN'))),
    "Infinity timestamp literal": (400, "invalid_json", raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": Infinity'))),
    "overflowing timestamp": (400, "invalid_json", raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": 1e400'))),
    "NaN as a string": (422, "validation_error", {"json": body(timestamp="NaN")}),
    "stream id too long": (422, "validation_error", {"json": body(stream_id="x" * 129)}),
    "stream id non-printable": (422, "validation_error", {"json": body(stream_id="car\x00one")}),
    "stream id newline": (422, "validation_error", {"json": body(stream_id="car\n")}),
    "stream id slash": (422, "validation_error", {"json": body(stream_id="a/b")}),
    "stream id empty": (422, "validation_error", {"json": body(stream_id="")}),
    "older timestamp": (409, "timestamp_not_increasing", {"json": body(timestamp=1.5)}),
    "equal timestamp": (409, "timestamp_not_increasing", {"json": body(timestamp=2.0)}),
    "bad query value": (422, "validation_error", {"json": body(), "params": {"flow_format": "xml"}}),
    "multipart nan timestamp": (422, "validation_error", form({"timestamp": "nan"})),
    "multipart inf pose": (422, "validation_error", form({"pose_x": "inf", "pose_y": "0", "pose_yaw": "0"})),
    "multipart partial pose": (422, "validation_error", form({"pose_x": "1", "pose_y": "0"})),
    "multipart unknown field": (422, "validation_error", form({"posex": "1"})),
    "multipart missing image": (422, "validation_error", form({}, image=None)),
    "urlencoded form": (415, "unsupported_media_type", {"data": {"stream_id": "s", "timestamp": "10"}}),
    "multipart image as text": (422, "validation_error", form({"image": "iVBOR"}, image=None)),
    "multipart truncated png": (422, "invalid_image", form({}, image=GOOD_PNG[:100])),
    "multipart colour": (422, "unsupported_image_format", form({}, image=png(np.zeros((128, 128, 3), np.uint8)))),
    "multipart empty file": (422, "invalid_image", form({}, image=b"")),
    "oversized body": (413, "request_too_large", {"json": body(image=base64.b64encode(bytes(300_000)).decode())}),
}


@pytest.fixture(scope="module")
def primed() -> TestClient:
    """One app for all cases, with stream `s` holding 2 frames (last timestamp 2.0)."""
    settings = Settings(threads=1, max_request_bytes=200_000)
    with TestClient(create_app(settings, runner=FakeRunner())) as client:
        wait_ready(client)
        for t in (1.0, 2.0):
            assert client.post("/detect", json=detect_json("s", t, FRAME, (t, 0.0, 0.0))).status_code == 200
        yield client


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_request_is_refused_and_changes_nothing(primed, case):
    status, code, request = CASES[case]
    before = primed.get("/streams").json()
    response = primed.post("/detect", **request)
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert error["code"] == code
    assert isinstance(error["message"], str) and len(error["message"]) > 5
    after = primed.get("/streams").json()
    assert after["count"] == before["count"] == 1
    assert stream_state(primed, "s") == {"stream_id": "s", "frames_buffered": 2, "frames_seen": 2,
                                          "last_timestamp": 2.0, "pose_source": "request",
                                          "state_bytes": stream_state(primed, "s")["state_bytes"]}


def test_wrong_size_message_names_the_accepted_sizes(primed):
    response = primed.post("/detect", json=body(image=b64png(np.zeros((64, 64), np.uint8))))
    assert "64x64" in response.json()["error"]["message"]
    assert "128x128 or 1152x1152" in response.json()["error"]["message"]


def test_streamed_body_over_the_limit_is_refused_without_content_length(primed):
    chunks = [b'{"stream_id": "s", "image": "'] + [b"A" * 50_000] * 6 + [b'"}']
    response = primed.post("/detect", content=iter(chunks), headers={"content-type": "application/json"})
    assert response.status_code == 413
    assert response.json()["error"]["code"] == "request_too_large"
    assert stream_state(primed, "s")["last_timestamp"] == 2.0


def test_delete_unknown_or_invalid_stream(primed):
    missing = primed.delete("/streams/never-seen")
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "stream_not_found"
    too_long = primed.delete("/streams/" + "x" * 129)
    assert too_long.status_code == 422 and too_long.json()["error"]["code"] == "validation_error"
    assert stream_state(primed, "s")["frames_seen"] == 2
