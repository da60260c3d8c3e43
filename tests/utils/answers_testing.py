"""The single in-process service the deployed ones are compared with, and the comparison of two /detect answers
of one model on one frame, field by field (timings aside)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

# Same model, same library versions, same CPU; the thread count may differ (onnxruntime's reductions then sum in
# another order: float32 differences of ~1e-6). The answer rounds boxes to 0.1 mm and flow to 1 mm.
BOX_ATOL, SCORE_ATOL, POLYGON_ATOL, FLOW_ATOL, POSE_ATOL = 2e-3, 1e-3, 0.05, 2e-3, 1e-4
EXACT = ("timestamp", "frames_used", "num_frames", "warming_up", "pose_source", "input")


def chain_free(boxes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """An answer's boxes with each track id's chain prefix taken off (it is new with every chain: two streams of the
    same frames number their tracks alike under different prefixes)."""
    return [box | {"track_id": box["track_id"].rsplit("-", 1)[1]} for box in boxes]


def comparable(answer: dict[str, Any]) -> dict[str, Any]:
    """The fields that must agree (not the stream id, timings, the runtime's self-description or the chains' track
    id prefixes)."""
    kept = {k: v for k, v in answer.items() if k not in ("stream_id", "timing")}
    return kept | {"boxes": chain_free(answer["boxes"])} if "boxes" in answer else kept


def assert_same_answer(served: dict[str, Any], reference: dict[str, Any]) -> None:
    assert set(served) == set(reference)
    for key in EXACT:
        assert served[key] == reference[key], (key, served[key], reference[key])
    assert served["model"]["checkpoint_sha256"] == reference["model"]["checkpoint_sha256"]
    assert (served["model"]["runtime"], served["model"]["precision"]) == ("onnxruntime", "fp32")
    assert (reference["model"]["runtime"], reference["model"]["precision"]) == ("onnxruntime", "fp32")
    np.testing.assert_allclose(
        [served["pose"][k] for k in "xy"] + [served["pose"]["yaw"]],
        [reference["pose"][k] for k in "xy"] + [reference["pose"]["yaw"]],
        atol=POSE_ATOL,
    )
    assert len(served["boxes"]) == len(reference["boxes"])
    for box, ref in zip(served["boxes"], reference["boxes"]):
        assert box["class"] == ref["class"]
        np.testing.assert_allclose(
            [box[k] for k in ("x", "y", "width", "length", "yaw")],
            [ref[k] for k in ("x", "y", "width", "length", "yaw")],
            atol=BOX_ATOL,
        )
        assert abs(box["score"] - ref["score"]) < SCORE_ATOL
        np.testing.assert_allclose(box["polygon"], ref["polygon"], atol=POLYGON_ATOL)
    assert (served["flow"] is None) == (reference["flow"] is None)
    if served["flow"] is not None:
        assert (
            served["flow"]["grid"] == reference["flow"]["grid"] and served["flow"]["pair"] == reference["flow"]["pair"]
        )
        np.testing.assert_allclose(served["flow"]["values"], reference["flow"]["values"], atol=FLOW_ATOL)


@contextlib.contextmanager
def in_process_service(**settings: Any) -> Iterator[TestClient]:
    """The service on the shipped model in this process (service.settings.Settings(**settings)), once ready."""
    from service.app import create_app
    from service.settings import Settings

    with TestClient(create_app(Settings(**settings))) as client:
        deadline = time.monotonic() + 120.0
        while client.get("/health/ready").status_code != 200:
            assert time.monotonic() < deadline, client.get("/health/ready").json()
            time.sleep(0.05)
        yield client
