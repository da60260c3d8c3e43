"""rafd.detect_client: every request form it builds is one the service takes and answers with the fields it was
given (the stream-id rule both follow: tests/rafd/test_protocol.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from rafd.detect_client import (
    DetectRequest,
    FrameFields,
    base64_png,
    detect_request,
    json_body,
    multipart_body,
    png_bytes,
)
from rafd.protocol import stream_id_from
from service import schemas
from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, blob_frame, wait_ready

KEY = "detect-client-key-0123456789"
PNG = png_bytes(blob_frame(128, [(60, 60, 200)]))


def test_json_bodies_are_what_the_service_schema_takes():
    full = FrameFields(2.5, "car-7", (1.0, -2.0, 0.25), previous_timestamp=2.25)
    for fields in (full, FrameFields(2.5)):
        body = schemas.DetectJson.model_validate_json(json_body(fields, base64_png(PNG)).content)
        assert (body.stream_id, body.timestamp, body.previous_timestamp) == (
            fields.stream_id,
            fields.timestamp,
            fields.previous_timestamp,
        )
        assert (None if body.pose is None else (body.pose.x, body.pose.y, body.pose.yaw)) == fields.pose


def test_headers_name_the_key_and_the_stream_only_when_given():
    plain = detect_request(json_body(FrameFields(1.0, "s"), ""))
    assert plain.headers == {"Content-Type": "application/json"} and plain.path == "/detect"
    named = detect_request(multipart_body(FrameFields(1.0), b""), flow=False, header_stream_id="s", api_key=KEY)
    assert named.path == "/detect?flow=false"
    assert named.headers["X-Stream-Id"] == "s" and named.headers["X-API-Key"] == KEY
    assert named.headers["Content-Type"].startswith("multipart/form-data; boundary=")


@pytest.fixture(scope="module")
def service() -> Iterator[TestClient]:
    settings = Settings(threads=1, api_keys=[f"tester:{KEY}"])
    with TestClient(create_app(settings, runner=FakeRunner(), odometry=FakeOdometry())) as client:
        wait_ready(client)
        yield client


def posted(service: TestClient, request: DetectRequest) -> dict:
    response = service.post(request.path, content=request.body, headers=request.headers)
    assert response.status_code == 200, response.text
    return response.json()


def in_header_only(fields: FrameFields) -> FrameFields:
    return FrameFields(fields.timestamp, None, fields.pose, fields.previous_timestamp)


FORMS = {
    "json, stream in the body and the header": lambda fields: detect_request(
        json_body(fields, base64_png(PNG)), header_stream_id=fields.stream_id, api_key=KEY
    ),
    "json, stream only in the header, no flow": lambda fields: detect_request(
        json_body(in_header_only(fields), base64_png(PNG)), flow=False, header_stream_id=fields.stream_id, api_key=KEY
    ),
    "multipart, stream in the body, no flow": lambda fields: detect_request(
        multipart_body(fields, PNG), flow=False, api_key=KEY
    ),
    "multipart, stream only in the header": lambda fields: detect_request(
        multipart_body(in_header_only(fields), PNG), header_stream_id=fields.stream_id, api_key=KEY
    ),
}


@pytest.mark.parametrize("form", sorted(FORMS))
@pytest.mark.parametrize("with_pose", [True, False], ids=["pose", "odometry"])
def test_each_form_round_trips_through_the_service(service: TestClient, form: str, with_pose: bool):
    stream = stream_id_from(f"{form}-{with_pose}")
    frames = [
        FrameFields(10.0, stream, (0.5, 1.0, 0.1) if with_pose else None),
        FrameFields(10.25, stream, (0.75, 1.5, 0.125) if with_pose else None, previous_timestamp=10.0),
    ]
    answers = [posted(service, FORMS[form](fields)) for fields in frames]
    assert [a["stream_id"] for a in answers] == [stream, stream]
    assert [a["timestamp"] for a in answers] == [10.0, 10.25] and [a["frames_used"] for a in answers] == [1, 2]
    assert {a["pose_source"] for a in answers} == {"request" if with_pose else "odometry"}
    if with_pose:
        assert [tuple(a["pose"][k] for k in ("x", "y", "yaw")) for a in answers] == [f.pose for f in frames]
    assert answers[0].get("stream_restarted") is None and answers[1].get("stream_restarted") is None
    assert (answers[1]["flow"] is None) is ("no flow" in form)  # the first frame has no pair: never flow
