"""Polar scans in /detect: a posted Navtech_Polar scan answers exactly as its Cartesian conversion does.

The service's one decode (service/body/images.py) converts a [576, 400] polar PNG with
rafd.preprocess.polar_to_cartesian to RADIATE's 1152 px scan; from there it is the Cartesian path.
"""

from __future__ import annotations

import base64
import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from rafd.preprocess import polar_to_cartesian
from rafd.scans.polar import RADIATE_POLAR_SHAPE
from service.app import create_app
from service.settings import Settings
from tests.utils.answers_testing import chain_free
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, b64png, png, wait_ready

POSES = [(0.0, 0.0, 0.0), (0.4, 1.5, 0.02)]


def polar_scan(seed: int) -> np.ndarray:
    """uint8 [576, 400] speckle with a few bright targets near the radar (inside a 128 px model crop)."""
    rng = np.random.default_rng(seed)
    polar = rng.integers(0, 30, RADIATE_POLAR_SHAPE, dtype=np.uint8)
    for azimuth in (10, 130, 260, 370):
        polar[40 + seed : 60 + seed, azimuth : azimuth + 6] = 220
    return polar


def comparable(answer: dict[str, Any]) -> dict[str, Any]:
    """The answer without what differs by design between the two posts: timings, stream id and posted format."""
    kept = {k: v for k, v in answer.items() if k not in ("timing", "stream_id")}
    kept["input"] = {k: v for k, v in answer["input"].items() if k != "posted_format"}
    return kept | {"boxes": chain_free(answer["boxes"])}


def post(client: TestClient, stream: str, t: int, image: bytes, multipart: bool = False) -> dict[str, Any]:
    x, y, yaw = POSES[t]
    if multipart:
        data = {
            "stream_id": stream,
            "timestamp": str(10.0 + t),
            "pose_x": str(x),
            "pose_y": str(y),
            "pose_yaw": str(yaw),
        }
        response = client.post("/detect", data=data, files={"image": ("scan.png", image, "image/png")})
    else:
        response = client.post(
            "/detect",
            json={
                "stream_id": stream,
                "timestamp": 10.0 + t,
                "pose": {"x": x, "y": y, "yaw": yaw},
                "image": base64.b64encode(image).decode("ascii"),
            },
        )
    assert response.status_code == 200, response.text
    return response.json()


@pytest.mark.parametrize("multipart", [False, True], ids=["json", "multipart"])
def test_polar_scan_answers_as_its_cartesian_conversion(client, multipart):
    for t in range(2):
        polar = polar_scan(t)
        from_polar = post(client, "polar", t, png(polar), multipart)
        from_cartesian = post(client, "cartesian", t, png(polar_to_cartesian(polar)), multipart)
        assert from_polar["input"]["posted_format"] == "polar"
        assert from_cartesian["input"]["posted_format"] == "cartesian"
        assert from_polar["input"]["posted_size"] == 1152  # polygons are in the converted scan's pixels
        assert from_polar["boxes"], "the targets near the radar must give boxes, or the comparison proves little"
        assert comparable(from_polar) == comparable(from_cartesian)


def test_polar_scan_differs_from_a_transposed_reading(client):
    """The conversion is really applied: the same pixels read as a Cartesian image answer differently."""
    polar = polar_scan(0)
    from_polar = post(client, "polar", 0, png(polar))
    rotated = post(client, "rotated", 0, png(polar_to_cartesian(polar[:, ::-1].copy())))  # azimuth reversed
    assert comparable(from_polar)["boxes"] != comparable(rotated)["boxes"]


def test_transposed_polar_scan_is_refused_naming_the_layout(client):
    response = client.post(
        "/detect",
        json={"stream_id": "t", "timestamp": 1.0, "image": b64png(np.zeros(RADIATE_POLAR_SHAPE[::-1], np.uint8))},
    )
    assert response.status_code == 422
    error = response.json()["error"]
    assert error["code"] == "unsupported_image_size"
    assert "576x400" in error["message"] and "400x576" in error["message"] and "Navtech_Polar" in error["message"]


def test_model_reports_the_accepted_polar_shape(client):
    assert client.get("/model").json()["accepted_polar_shape"] == [576, 400]


def test_polar_scan_is_refused_where_a_full_radiate_scan_is(settings):
    """A model at another resolution takes no full RADIATE scan, so no polar one either (it converts to one)."""
    config = dataclasses.replace(FakeRunner().config, resolution=0.3)
    with TestClient(create_app(settings, runner=FakeRunner(config), odometry=FakeOdometry())) as client:
        wait_ready(client)
        assert client.get("/model").json()["accepted_polar_shape"] is None
        response = client.post("/detect", json={"stream_id": "p", "timestamp": 1.0, "image": b64png(polar_scan(0))})
        assert response.status_code == 422 and response.json()["error"]["code"] == "unsupported_image_size"
        assert "polar" not in response.json()["error"]["message"]


# --- the real polar scans of tiny_foggy, on the shipped model -------------------------------------------------


@pytest.fixture(scope="module")
def shipped_client() -> Iterator[TestClient]:
    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner

    runner = OnnxRunner(default_onnx(), threads=1)
    with TestClient(create_app(Settings(threads=1, score_threshold=0.3), runner=runner)) as client:
        wait_ready(client, timeout=60.0)
        yield client


def test_real_polar_scans_answer_as_their_cartesian_conversion(shipped_client, radiate_polar_sample: Path):
    """Both real polar scans, posted as they are on disk, without poses (the service's odometry on the converted
    scans): every answer equals the one for the Cartesian PNG of the same conversion."""
    paths = sorted((radiate_polar_sample / "Navtech_Polar").glob("*.png"))
    assert len(paths) >= 2
    for t, path in enumerate(paths):
        polar = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert polar.shape == RADIATE_POLAR_SHAPE
        body = {"timestamp": 10.0 + t}
        from_polar = shipped_client.post(
            "/detect", json={**body, "stream_id": "real-polar", "image": b64png(polar)}
        ).json()
        raw = shipped_client.post(
            "/detect",
            json={**body, "stream_id": "real-polar-file", "image": base64.b64encode(path.read_bytes()).decode("ascii")},
        ).json()
        from_cartesian = shipped_client.post(
            "/detect", json={**body, "stream_id": "real-cartesian", "image": b64png(polar_to_cartesian(polar))}
        ).json()
        assert from_polar["input"]["posted_format"] == raw["input"]["posted_format"] == "polar"
        assert from_polar["pose_source"] == "odometry"
        assert comparable(from_polar) == comparable(from_cartesian) == comparable(raw)


@pytest.mark.parametrize("input_size, range_m", [(128, None), (256, 30.0), (256, 10.0), (640, 60.0)])
def test_only_what_is_looked_at_is_converted_and_it_equals_the_whole_conversion(input_size, range_m):
    """The service converts a polar scan only over the square it detects over (the whole scan, or within the range
    asked) and odometry's view (512 px): the very pixels of the whole 1152 px conversion's centre."""
    from rafd.preprocess import model_crop
    from rafd.runtime.view import View
    from service.body.images import decode_frame

    polar = polar_scan(3)
    whole = polar_to_cartesian(polar)
    side = View.of(1152, input_size, 0.173611, 4, range_m).side_px
    decoded = decode_frame(png(polar), input_size, 0.173611, covered=lambda posted: side)
    assert decoded.posted_size == 1152 and decoded.covered.shape == (side, side)
    np.testing.assert_array_equal(decoded.covered, model_crop(whole, side))
    np.testing.assert_array_equal(decoded.odometry_view, model_crop(whole, 512))
