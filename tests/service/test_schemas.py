"""Every answer is what the OpenAPI document says: real /detect, /model, /streams and health answers validated
against the response models with unknown fields forbidden (service.schemas.Answer), on the FakeRunner and on the
shipped model with real scans."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import BaseModel

from service.app import create_app
from service.schemas import DetectResponse, Liveness, ModelInfo, Readiness, StreamsResponse
from service.settings import Settings
from tests.utils.service_testing import blob_frame, detect_json, wait_ready


def validate(model: type[BaseModel], answer: dict[str, Any]) -> BaseModel:
    """Validate an answer as parsed from JSON; an unknown or missing field raises."""
    return model.model_validate(answer)


def declared_model(client: TestClient, path: str, method: str = "get") -> str:
    """The component the OpenAPI document names for a route's 200 answer."""
    schema = client.get("/openapi.json").json()["paths"][path][method]["responses"]["200"]["content"]
    return schema["application/json"]["schema"]["$ref"].rsplit("/", 1)[-1]


def check_answers(client: TestClient, frames: list[dict[str, Any]], multipart: bool = False) -> list[DetectResponse]:
    answers = []
    for body in frames:
        if multipart:
            response = client.post("/detect", data=body["data"], files=body["files"])
        else:
            response = client.post("/detect", json=body)
        assert response.status_code == 200, response.text
        answers.append(validate(DetectResponse, response.json()))
    validate(ModelInfo, client.get("/model").json())
    validate(StreamsResponse, client.get("/streams").json())
    validate(Liveness, client.get("/health/live").json())
    validate(Readiness, client.get("/health/ready").json())
    return answers  # type: ignore[return-value]


def test_the_openapi_document_names_the_answer_models(client: TestClient):
    assert declared_model(client, "/detect", "post") == "DetectResponse"
    assert declared_model(client, "/model") == "ModelInfo"
    assert declared_model(client, "/streams") == "StreamsResponse"
    assert declared_model(client, "/health/ready") == "Readiness"


def test_fake_runner_answers_match_the_schema_with_boxes_and_flow(client: TestClient):
    frames = [
        detect_json("s", float(t), blob_frame(128, [(40 + 4 * t, 60, 255)]), (0.0, 2.0 * t, 0.0)) for t in range(3)
    ]
    answers = check_answers(client, frames)
    assert any(a.boxes for a in answers) and answers[-1].flow is not None  # boxes and flow were checked too


def test_an_unknown_field_in_an_answer_is_refused():
    """The guard itself: an answer with one field more than the schema fails validation."""
    from pydantic import ValidationError

    answer = {"status": "ready", "model_version": "1", "extra": 1}
    with pytest.raises(ValidationError, match="extra"):
        validate(Readiness, answer)


def test_shipped_model_answers_on_real_scans_match_the_schema(radiate_sample: Path):
    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner

    app = create_app(Settings(threads=1), runner=OnnxRunner(default_onnx(), threads=1))
    scans = sorted((radiate_sample / "Navtech_Cartesian").glob("*.png"))[:3]
    frames = [
        {"data": {"stream_id": "real", "timestamp": str(t)}, "files": {"image": (p.name, p.read_bytes(), "image/png")}}
        for t, p in enumerate(scans, 1)
    ]
    with TestClient(app) as client:
        wait_ready(client, timeout=60)
        answers = check_answers(client, frames, multipart=True)
    assert [a.frames_used for a in answers] == [1, 2, 3]
    assert answers[-1].model.runtime == "onnxruntime" and answers[-1].model.precision == "fp32"
