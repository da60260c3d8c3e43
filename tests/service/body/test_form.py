"""The multipart form is the JSON body's fields, defined once (service.schemas.DetectBody): the OpenAPI document's
two request forms list the same fields, and the parser accepts every field the document lists."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.body.form import form_field_names, form_groups
from service.schemas import DetectBody, Pose
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import blob_frame, png, stream_state, wait_ready

FRAME = png(blob_frame(128, [(8, 8, 255)]))


@pytest.fixture
def client():
    with TestClient(create_app(Settings(threads=1), runner=FakeRunner())) as test_client:
        wait_ready(test_client)
        yield test_client


def _request_forms(client: TestClient) -> tuple[dict, dict]:
    document = client.get("/openapi.json").json()
    content = document["paths"]["/detect"]["post"]["requestBody"]["content"]
    json_schema = content["application/json"]["schema"]
    if "$ref" in json_schema:
        json_schema = document["components"]["schemas"][json_schema["$ref"].rsplit("/", 1)[-1]]
    return json_schema, content["multipart/form-data"]["schema"]


def test_both_openapi_forms_list_every_field_of_the_body(client):
    json_schema, form = _request_forms(client)
    flattened = set()
    for name in DetectBody.model_fields:
        if name == "pose":
            flattened |= {f"pose_{axis}" for axis in Pose.model_fields}
        else:
            flattened.add(name)
    assert set(json_schema["properties"]) == set(DetectBody.model_fields) | {"image"}
    assert set(form["properties"]) == flattened | {"image"} == set(form_field_names()) | {"image"}
    assert "previous_timestamp" in form["properties"]  # the form once lacked it
    assert set(form["required"]) == {"timestamp", "image"}
    for name, prop in form["properties"].items():  # typed and described, so a generated client can send it
        assert prop["type"] in ("number", "string") and prop["description"], name


def test_the_parser_accepts_every_field_the_document_lists(client):
    _, form = _request_forms(client)
    values = {"stream_id": "every", "timestamp": "2.0", "previous_timestamp": "1.0"}
    values |= {name: "0.5" for name in form_groups()["pose"]}
    native_only = {"range_resolution_m": "0.0438"}  # read, then refused for a square image (its meaning, not its form)
    assert set(values) | set(native_only) | {"image"} == set(form["properties"])
    refused = client.post("/detect", data=values | native_only, files={"image": ("f.png", FRAME, "image/png")})
    assert refused.status_code == 422 and "native scans only" in refused.json()["error"]["message"]
    first = client.post(
        "/detect",
        data={"stream_id": "every", "timestamp": "1.0", "pose_x": "0", "pose_y": "0", "pose_yaw": "0"},
        files={"image": ("f.png", FRAME, "image/png")},
    )
    assert first.status_code == 200, first.text
    answer = client.post("/detect", data=values, files={"image": ("f.png", FRAME, "image/png")})
    assert answer.status_code == 200, answer.text
    assert answer.json()["pose"] == {"x": 0.5, "y": 0.5, "yaw": 0.5}
    assert stream_state(client, "every")["frames_seen"] == 2


def test_a_field_outside_the_document_is_refused(client):
    refused = client.post(
        "/detect",
        data={"stream_id": "x", "timestamp": "1.0", "pose_yw": "0.1"},
        files={"image": ("f.png", FRAME, "image/png")},
    )
    assert refused.status_code == 422 and refused.json()["error"]["code"] in ("validation_error", "invalid_multipart")
