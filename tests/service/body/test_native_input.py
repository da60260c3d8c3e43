"""Native scans (Oxford Radar RobotCar, Boreas) in /detect: posted as they are on disk, they answer exactly as their
Cartesian conversion does (rafd.scans.native.to_cartesian, the one decode); bad native files are 422; GET /model says
so.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from rafd.scans.native import parse_native_scan, to_cartesian
from service.app import create_app
from tests.rafd.scans.test_native import native_png
from tests.utils.answers_testing import chain_free
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, b64png, wait_ready


def native_scan(seed: int) -> np.ndarray:
    """A native Oxford-layout scan with returns inside the FakeRunner's 128 px crop (about +-11 m)."""
    return native_png(
        3768,
        [(30.0 + 40 * seed, 6.0), (200.0, 8.0 + seed)],
        0.0432,
        start_us=1_547_131_046_000_000 + 250_000 * seed,
        size_m=1.5,
    )


def post(client: TestClient, stream: str, t: int, image: np.ndarray) -> dict[str, Any]:
    response = client.post(
        "/detect",
        json={
            "stream_id": stream,
            "timestamp": 10.0 + t,
            "image": b64png(image),
            "pose": {"x": 0.0, "y": 1.5 * t, "yaw": 0.0},
        },
    )
    assert response.status_code == 200, response.text
    return response.json()


def comparable(answer: dict[str, Any]) -> dict[str, Any]:
    kept = {k: v for k, v in answer.items() if k not in ("timing", "stream_id")}
    kept["input"] = {
        k: v for k, v in answer["input"].items() if k not in ("posted_format", "native_format", "native_range_bin_m")
    }
    return kept | {"boxes": chain_free(answer["boxes"])}


def test_a_native_scan_answers_as_its_cartesian_conversion(client: TestClient):
    for t in range(2):
        native = native_scan(t)
        from_native = post(client, "native", t, native)
        from_cartesian = post(client, "cartesian", t, to_cartesian(parse_native_scan(native)))
        assert from_native["input"]["posted_format"] == "native" and from_native["input"]["posted_size"] == 1152
        assert from_native["boxes"], "the returns near the radar must give boxes, or the comparison proves little"
        assert comparable(from_native) == comparable(from_cartesian)


def test_a_native_scan_whose_header_does_not_read_is_refused(client: TestClient):
    broken = native_scan(0)
    broken[:, :8] = broken[::-1, :8]  # timestamps run backwards
    response = client.post("/detect", json={"stream_id": "b", "timestamp": 1.0, "image": b64png(broken)})
    assert response.status_code == 422 and response.json()["error"]["code"] == "invalid_image"
    assert "timestamps decrease" in response.json()["error"]["message"]


def test_the_model_says_native_scans_are_accepted(client: TestClient):
    native = client.get("/model").json()["accepted_native"]
    assert native["formats"]["oxford"] == 0.0432 and "boreas" in native["formats"]


def test_native_scans_are_refused_where_a_full_radiate_scan_is(settings):
    config = dataclasses.replace(FakeRunner().config, resolution=0.3)
    with TestClient(create_app(settings, runner=FakeRunner(config), odometry=FakeOdometry())) as client:
        wait_ready(client)
        assert client.get("/model").json()["accepted_native"] is None
        response = client.post("/detect", json={"stream_id": "n", "timestamp": 1.0, "image": b64png(native_scan(0))})
        assert response.status_code == 422 and response.json()["error"]["code"] == "unsupported_image_size"


@pytest.mark.slow
def test_real_oxford_scans_post_without_poses_on_the_shipped_model(oxford_sample: Path):
    """The real native PNGs as they are on disk, multipart, no pose: 200 answers in the converted scan's pixels, the
    odometry's forward motion close to the ground truth's (2.3-2.4 m per scan here)."""
    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner
    from service.settings import Settings

    paths = sorted((oxford_sample / "radar").glob("*.png"))[:3]
    with TestClient(create_app(Settings(threads=1), runner=OnnxRunner(default_onnx(), threads=1))) as client:
        wait_ready(client, timeout=60.0)
        answers = []
        for t, path in enumerate(paths):
            files = {"image": (path.name, path.read_bytes(), "image/png")}
            response = client.post("/detect", data={"stream_id": "oxford", "timestamp": str(t)}, files=files)
            assert response.status_code == 200, response.text
            answers.append(response.json())
    assert all(a["input"]["posted_format"] == "native" and a["pose_source"] == "odometry" for a in answers)
    assert 4.4 < answers[2]["pose"]["y"] < 5.0  # two steps of about 2.3-2.4 m forward


# ---------------------------------------------------------------- bounded by a real sensor (issue 40)
def zero_png(width: int, height: int) -> bytes:
    """An all-zero 8-bit grey PNG of any size, written by hand (a 400 x 400,000 one is 389 KB; no encoder needed)."""
    import struct
    import zlib

    from service.body.png import PNG_SIGNATURE, png_chunk

    header = png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
    data = zlib.compressobj(9)
    row = bytes(1 + width)
    compressed = b"".join(data.compress(row) for _ in range(height)) + data.flush()
    return PNG_SIGNATURE + header + png_chunk(b"IDAT", compressed) + png_chunk(b"IEND", b"")


def test_a_native_scan_wider_than_a_sensor_is_refused_from_its_header(client: TestClient, monkeypatch):
    """The finding: an all-zero 400 x 400,000 PNG (389 KB) took 15 s and 3.3 GB. Now its header is enough: 422
    before anything is inflated (the bounded inflate is never reached), JSON and multipart alike."""
    import service.body.png

    def never(*args: object) -> bytes:
        raise AssertionError("the image was inflated")

    monkeypatch.setattr(service.body.png, "inflate_idat", never)
    wide = zero_png(400_000, 400)
    assert len(wide) < 400_000
    as_json = client.post("/detect", json={"stream_id": "w", "timestamp": 1.0, "image": b64png_bytes(wide)})
    as_form = client.post(
        "/detect", data={"stream_id": "w", "timestamp": "1"}, files={"image": ("w.png", wide, "image/png")}
    )
    for response in (as_json, as_form):
        assert response.status_code == 422, response.text
        assert response.json()["error"]["code"] == "unsupported_image_size"
        assert "at most 6848 range bins" in response.json()["error"]["message"]
    tall = client.post(
        "/detect", json={"stream_id": "w", "timestamp": 1.0, "image": b64png_bytes(zero_png(11 + 3768, 401))}
    )
    assert tall.status_code == 422 and tall.json()["error"]["code"] == "unsupported_image_size"


def test_the_native_bound_is_a_setting_for_other_sensors(settings):
    """RAFD_NATIVE_MAX_RANGE_BINS admits a wider sensor (its header checked as any native scan's)."""
    wide = native_png(8000, [(30.0, 6.0)], 0.0432, start_us=1_547_131_046_000_000)
    default = settings.model_copy()
    raised = settings.model_copy(update={"native_max_range_bins": 8000})
    for chosen, status in ((default, 422), (raised, 200)):
        with TestClient(create_app(chosen, runner=FakeRunner(), odometry=FakeOdometry())) as client:
            wait_ready(client)
            response = client.post("/detect", json={"stream_id": "n", "timestamp": 1.0, "image": b64png(wide)})
            assert response.status_code == status, response.text
            if status == 200:
                assert (
                    client.get("/model")
                    .json()["accepted_native"]["columns"]
                    .endswith("at most 8000 range bins (RAFD_NATIVE_MAX_RANGE_BINS)")
                )


@pytest.mark.parametrize(
    "case, rule",
    [
        ("angles all equal", "encoder_one_turn"),
        ("angles reversed", "encoder_one_turn"),
        ("times all equal", "azimuth_time_increasing"),
        ("times at INT64_MAX", "azimuth_time_range"),
        ("a sweep of 10 s", "sweep_period"),
    ],
)
def test_a_degenerate_native_header_is_422_naming_the_rule(client: TestClient, case: str, rule: str):
    """The finding: all-zero angles moved the pose -2.80 m instead of -0.05 m, and the chain stayed offset. Now the
    frame is refused, naming the rule, and the stream keeps what it had."""
    from tests.rafd.scans.test_native import DEGENERATE_HEADERS, _with_header

    times, encoder, _ = DEGENERATE_HEADERS[case]
    first = post(client, "deg", 0, native_scan(0))
    bad = _with_header(native_scan(1), times, encoder)
    response = client.post("/detect", json={"stream_id": "deg", "timestamp": 11.0, "image": b64png(bad)})
    assert response.status_code == 422 and response.json()["error"]["code"] == "invalid_image"
    assert f"rule {rule}" in response.json()["error"]["message"]
    after = post(client, "deg", 1, native_scan(1))
    assert after["frames_used"] == first["frames_used"] + 1  # the refused frame left no trace


def b64png_bytes(data: bytes) -> str:
    import base64

    return base64.b64encode(data).decode("ascii")


def test_the_real_boreas_rt_scan_answers_as_its_boreas_rt_conversion(client: TestClient, boreas_rt_scan: Path):
    """The real RAS6 Doppler scan posted as it is on disk: read as boreas-rt (its chirp column not taken for a valid
    flag, every azimuth measured), it answers exactly as its boreas-rt Cartesian conversion; the old reading (a valid
    flag: half the azimuths unmeasured) converts to another scan."""
    import cv2

    native = cv2.imread(str(boreas_rt_scan), cv2.IMREAD_UNCHANGED)
    from_native = post(client, "boreas-rt", 0, native)
    converted = to_cartesian(parse_native_scan(native, "boreas-rt"))
    from_cartesian = post(client, "boreas-rt-cartesian", 0, converted)
    assert from_native["input"]["posted_format"] == "native"
    assert comparable(from_native) == comparable(from_cartesian)
    as_valid_flag = to_cartesian(parse_native_scan(native, "boreas-2021"))
    assert np.abs(as_valid_flag.astype(int) - converted.astype(int)).max() > 50


# ---------------------------------------------------------------- the sensor's own range bin (issue 60)
def test_a_posted_range_resolution_replaces_the_guess_from_the_width(client: TestClient):
    """range_resolution_m (JSON and multipart alike) is the bin size used: the answer equals the Cartesian conversion
    at that bin size, says so in input.native_range_bin_m, and differs from the width's guess (Oxford's 0.0432)."""
    from rafd.detect_client import FrameFields, base64_png, json_body, multipart_body, png_bytes
    from rafd.scans.native import NATIVE_FORMATS

    native = native_scan(0)
    doubled = NATIVE_FORMATS["oxford"].with_range_bin(0.0864)
    reference = post(client, "reference", 0, to_cartesian(parse_native_scan(native, doubled)))
    guessed = post(client, "guessed", 0, native)
    assert guessed["input"]["native_format"] == "oxford" and guessed["input"]["native_range_bin_m"] == 0.0432
    for form, stream in (("json", "told-json"), ("multipart", "told-form")):
        fields = FrameFields(10.0, stream, (0.0, 0.0, 0.0), range_resolution_m=0.0864)
        body = (
            json_body(fields, base64_png(png_bytes(native)))
            if form == "json"
            else multipart_body(fields, png_bytes(native))
        )
        response = client.post("/detect", content=body.content, headers={"Content-Type": body.content_type})
        assert response.status_code == 200, response.text
        told = response.json()
        assert told["input"]["native_range_bin_m"] == 0.0864 and told["input"]["native_format"] == "oxford"
        assert comparable(told) == comparable(reference)
        assert told["boxes"] != guessed["boxes"]


@pytest.mark.parametrize(
    "value, image, message",
    [
        (0.0, "native", "greater than or equal to 0.001"),
        (-0.0432, "native", "greater than or equal to 0.001"),
        (43.2, "native", "less than or equal to 1"),
        (0.0432, "cartesian", "native scans only"),
    ],
)
def test_a_bad_range_resolution_is_refused(client: TestClient, value: float, image: str, message: str):
    posted = native_scan(0) if image == "native" else np.zeros((128, 128), np.uint8)
    body = {"stream_id": "bad-bin", "timestamp": 1.0, "image": b64png(posted), "range_resolution_m": value}
    response = client.post("/detect", json=body)
    assert response.status_code == 422, response.text
    assert response.json()["error"]["code"] == "validation_error" and message in response.json()["error"]["message"]
    assert client.get("/streams").json()["streams"] == []  # refused before it reached the stream
