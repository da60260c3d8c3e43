"""Every malformed request gets a 4xx {"error": {"code", "message"}} and changes no stream, not even its idle time.

Issue 14 finding 8 (looser than documented) is reproduced here case by case: JSON type coercion, 1-bit PNGs,
duplicate multipart fields, undocumented multipart faults.
"""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.png_testing import chunk, grey_png, other_format_png, text_chunks
from tests.utils.service_testing import b64png, blob_frame, detect_json, png, stream_state, wait_ready

FRAME = blob_frame(128, [(8, 8, 255)])
GOOD_PNG = png(FRAME)
PRIMED_AT = 1000.0


class Clock:
    def __init__(self) -> None:
        self.now = PRIMED_AT

    def __call__(self) -> float:
        return self.now


def body(**changes):
    base = detect_json("s", 10.0, FRAME, (1.0, 2.0, 0.1))
    base.update(changes)
    return {k: v for k, v in base.items() if v is not ...}


def raw_json(text: str) -> dict:
    return {"content": text.encode(), "headers": {"content-type": "application/json"}}


def form(data: dict, image: bytes | None = GOOD_PNG, extra: list | None = None) -> dict:
    """multipart/form-data: plain fields as (None, value) parts, so it stays multipart without a file."""
    fields = {"stream_id": "s", "timestamp": "10.0", **data}
    files = [(k, (None, v)) for k, v in fields.items()]
    if image is not None:
        files.append(("image", ("f.png", image, "image/png")))
    return {"files": files + (extra or [])}


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def raw_multipart(body: bytes, content_type: str = "multipart/form-data; boundary=XyZ") -> dict:
    return {"content": body, "headers": {"content-type": content_type}}


def multipart_part(name: str, value: bytes, filename: str | None = None) -> bytes:
    file = f'; filename="{filename}"' if filename else ""
    return (
        b'--XyZ\r\nContent-Disposition: form-data; name="'
        + name.encode()
        + b'"'
        + file.encode()
        + b"\r\n\r\n"
        + value
        + b"\r\n"
    )


def flipped(data: bytes, index: int) -> bytes:
    data = bytearray(data)
    data[index] ^= 1
    return bytes(data)


def split_idat_run() -> bytes:
    """A PNG whose IDAT chunks are interrupted by a text chunk (the spec wants them consecutive)."""
    noise = np.random.default_rng(0).integers(0, 255, (128, 128), dtype=np.uint8)
    data = grey_png(noise, idat_size=100)
    first_idat_end = 33 + 12 + 100
    return data[:first_idat_end] + chunk(b"tEXt", b"a\x00b") + data[first_idat_end:]


GOOD_BODY = json.dumps(body())
CASES = {
    "wrong content type": (
        415,
        "unsupported_media_type",
        {"content": GOOD_BODY.encode(), "headers": {"content-type": "text/plain"}},
    ),
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
    # issue 34 finding 6: binascii.a2b_base64 raised ValueError (not binascii.Error) on non-ASCII text: 500 before
    "non-ASCII base64": (422, "invalid_image", {"json": body(image="éééé")}),
    "non-ASCII inside valid base64": (
        422,
        "invalid_image",
        {"json": body(image=b64(GOOD_PNG)[:40] + "é" + b64(GOOD_PNG)[41:])},
    ),
    "non-ASCII data url": (422, "invalid_image", {"json": body(image="data:image/png;base64,ééé")}),
    "base64 not an image": (422, "invalid_image", {"json": body(image=base64.b64encode(b"hello radar").decode())}),
    "empty image": (422, "validation_error", {"json": body(image="")}),
    "truncated png": (
        422,
        "invalid_image",
        {"json": body(image=base64.b64encode(GOOD_PNG[: len(GOOD_PNG) // 2]).decode())},
    ),
    "jpeg not png": (
        422,
        "invalid_image",
        {"json": body(image=base64.b64encode(b"\xff\xd8\xff\xe0" + bytes(64)).decode())},
    ),
    "wrong size": (422, "unsupported_image_size", {"json": body(image=b64png(np.zeros((64, 64), np.uint8)))}),
    "not square": (422, "unsupported_image_size", {"json": body(image=b64png(np.zeros((1152, 1000), np.uint8)))}),
    "colour image": (422, "unsupported_image_format", {"json": body(image=b64png(np.zeros((128, 128, 3), np.uint8)))}),
    "grey + alpha": (422, "unsupported_image_format", {"json": body(image=b64png(np.zeros((128, 128, 4), np.uint8)))}),
    "16-bit image": (422, "unsupported_image_format", {"json": body(image=b64png(np.zeros((128, 128), np.uint16)))}),
    "NaN pose literal": (400, "invalid_json", raw_json(GOOD_BODY.replace('"x": 1.0', '"x": NaN'))),
    "Infinity timestamp literal": (
        400,
        "invalid_json",
        raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": Infinity')),
    ),
    "overflowing timestamp": (
        400,
        "invalid_json",
        raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": 1e400')),
    ),
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
    # finding 8: no JSON type coercion
    "timestamp true": (422, "validation_error", {"json": body(timestamp=True)}),
    "timestamp numeric string": (422, "validation_error", {"json": body(timestamp="11.5")}),
    "timestamp null": (422, "validation_error", {"json": body(timestamp=None)}),
    "pose x string": (422, "validation_error", {"json": body(pose={"x": "1.0", "y": 2.0, "yaw": 0.1})}),
    "pose yaw boolean": (422, "validation_error", {"json": body(pose={"x": 1.0, "y": 2.0, "yaw": False})}),
    "pose unknown key": (422, "validation_error", {"json": body(pose={"x": 1.0, "y": 2.0, "yaw": 0.1, "z": 0})}),
    "stream id a number": (422, "validation_error", {"json": body(stream_id=5)}),
    "image not a string": (422, "validation_error", {"json": body(image=[1, 2])}),
    "duplicate json key": (
        422,
        "validation_error",
        raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": 10.0, "timestamp": 11.0')),
    ),
    "huge integer timestamp": (  # beyond a double: out of range for orjson like 1e400
        400,
        "invalid_json",
        raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": 1' + "0" * 400)),
    ),
    "overlong integer literal": (
        400,
        "invalid_json",
        raw_json(GOOD_BODY.replace('"timestamp": 10.0', '"timestamp": 1' + "0" * 5000)),
    ),
    "deeply nested json": (422, "validation_error", raw_json("[" * 100_000 + "]" * 100_000)),  # refused unparsed
    # finding 8: 8-bit greyscale PNG only, refused from the header
    "1-bit png": (422, "unsupported_image_format", {"json": body(image=b64(other_format_png(128, 128, 1, 0)))}),
    "palette png": (422, "unsupported_image_format", {"json": body(image=b64(other_format_png(128, 128, 8, 3)))}),
    "4-bit grey png": (422, "unsupported_image_format", {"json": body(image=b64(other_format_png(128, 128, 4, 0)))}),
    "base64 with line breaks": (422, "invalid_image", {"json": body(image=base64.encodebytes(GOOD_PNG).decode())}),
    "data url of another type": (422, "invalid_image", {"json": body(image="data:image/jpeg;base64," + b64(GOOD_PNG))}),
    # finding 1: chunk structure refused before decoding
    "too many ancillary chunks": (
        422,
        "invalid_image",
        {"json": body(image=b64(grey_png(FRAME, before_idat=text_chunks(17, 100))))},
    ),
    "ancillary chunks too large": (
        422,
        "invalid_image",
        {"json": body(image=b64(grey_png(FRAME, before_idat=text_chunks(1, 70_000, compressed=False))))},
    ),
    "image data inflating past its header": (
        422,
        "invalid_image",
        {"json": body(image=b64(grey_png(FRAME, extra_compressed=1_000_000)))},
    ),
    "image data short of its header": (
        422,
        "invalid_image",
        {"json": body(image=b64(grey_png(FRAME[:100], declared=(128, 128))))},
    ),
    "chunk running past the end": (
        422,
        "invalid_image",
        {"json": body(image=b64(grey_png(FRAME)[:60] + grey_png(FRAME)[-12:]))},
    ),
    "bytes after IEND": (422, "invalid_image", {"json": body(image=b64(grey_png(FRAME, trailing=b"x" * 10)))}),
    "unknown critical chunk": (
        422,
        "invalid_image",
        {"json": body(image=b64(grey_png(FRAME, before_idat=chunk(b"ABCD", b"1"))))},
    ),
    "split IDAT run": (422, "invalid_image", {"json": body(image=b64(split_idat_run()))}),
    "bad IDAT crc": (422, "invalid_image", {"json": body(image=b64(flipped(GOOD_PNG, -13)))}),  # last IDAT's CRC
    "corrupt image data": (422, "invalid_image", {"json": body(image=b64(flipped(GOOD_PNG, -20)))}),  # its adler32
    # finding 8: duplicate multipart fields refused; multipart faults have documented codes
    "multipart duplicate field": (422, "validation_error", form({}, extra=[("timestamp", (None, "11.0"))])),
    "multipart duplicate image": (
        422,
        "validation_error",
        form({}, extra=[("image", ("g.png", GOOD_PNG, "image/png"))]),
    ),
    "multipart stream id as a file": (
        422,
        "validation_error",
        form({}, extra=[("pose_x", ("x.txt", b"1", "text/plain"))]),
    ),
    "multipart timestamp with spaces": (422, "validation_error", form({"timestamp": " 10.5"})),
    "multipart timestamp underscores": (422, "validation_error", form({"timestamp": "1_000"})),
    "multipart timestamp true": (422, "validation_error", form({"timestamp": "true"})),
    "multipart field too long": (422, "validation_error", form({"stream_id": "s" * 2000})),
    "multipart not utf-8": (422, "validation_error", form({"stream_id": b"\xff\xfe"})),
    "multipart no boundary": (400, "invalid_multipart", raw_multipart(b"--XyZ--\r\n", "multipart/form-data")),
    "multipart garbage": (400, "invalid_multipart", raw_multipart(b"this is not multipart at all")),
    "multipart no closing boundary": (400, "invalid_multipart", raw_multipart(multipart_part("stream_id", b"s"))),
    "multipart part without name": (
        400,
        "invalid_multipart",
        raw_multipart(b"--XyZ\r\nContent-Disposition: form-data\r\n\r\nx\r\n--XyZ--\r\n"),
    ),
    "multipart empty body": (400, "empty_body", raw_multipart(b"")),
    # the stream named outside the body must agree with the body
    "header stream id differs": (422, "stream_id_mismatch", {"json": body(), "headers": {"X-Stream-Id": "other"}}),
    "header stream id invalid": (422, "validation_error", {"json": body(), "headers": {"X-Stream-Id": "a/b"}}),
    "no stream id anywhere": (422, "validation_error", {"json": body(stream_id=...)}),
}
# The reason, for cases where the code alone could be right for the wrong reason.
MESSAGES = {
    "too many ancillary chunks": "ancillary chunks",
    "ancillary chunks too large": "ancillary chunks",
    "image data inflating past its header": "inflates to more than",
    "image data short of its header": "truncated (",
    "bytes after IEND": "after its IEND",
    "unknown critical chunk": "critical chunk",
    "split IDAT run": "consecutive",
    "bad IDAT crc": "could not be decoded",
    "corrupt image data": "corrupt",
    "1-bit png": "1-bit greyscale",
    "palette png": "8-bit palette",
    "4-bit grey png": "4-bit greyscale",
    "duplicate json key": "more than once",
    "deeply nested json": "more than a detect request can have",
    "non-ASCII base64": "not valid base64",
    "non-ASCII inside valid base64": "base64",
    "multipart duplicate field": "more than once",
    "multipart duplicate image": "more than once",
    "timestamp true": "valid number",
    "timestamp numeric string": "valid number",
    "multipart timestamp true": "finite number",
    "no stream id anywhere": "X-Stream-Id",
}
PATH_CASES = {
    "path and body differ": (422, "stream_id_mismatch", "/streams/other/detect", {"json": body()}),
    "path and header differ": (
        422,
        "stream_id_mismatch",
        "/streams/s/detect",
        {"json": body(stream_id=...), "headers": {"X-Stream-Id": "t"}},
    ),
    "older timestamp on the path form": (
        409,
        "timestamp_not_increasing",
        "/streams/s/detect",
        {"json": body(stream_id=..., timestamp=1.0)},
    ),
}


@pytest.fixture(scope="module")
def primed() -> tuple[TestClient, Clock, dict]:
    """One app for all cases, with stream `s` holding 2 frames (last timestamp 2.0), accepted at clock PRIMED_AT."""
    clock = Clock()
    settings = Settings(threads=1, max_request_bytes=200_000)
    with TestClient(create_app(settings, runner=FakeRunner(), clock=clock)) as client:
        wait_ready(client)
        for t in (1.0, 2.0):
            assert client.post("/detect", json=detect_json("s", t, FRAME, (t, 0.0, 0.0))).status_code == 200
        yield client, clock, stream_state(client, "s")


def assert_refused_without_change(primed, response, status: int, code: str) -> None:
    client, clock, state = primed
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert error["code"] == code
    assert isinstance(error["message"], str) and 5 < len(error["message"]) <= 512
    body = client.get("/streams").json()
    assert body["count"] == 1
    assert stream_state(client, "s") == state
    # Not even its idle time: the clock moved on since the stream's last ACCEPTED frame.
    assert body["streams"][0]["idle_s"] == pytest.approx(clock.now - PRIMED_AT)


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_request_is_refused_and_changes_nothing(primed, case):
    status, code, request = CASES[case]
    primed[1].now += 1.0
    response = primed[0].post("/detect", **request)
    assert_refused_without_change(primed, response, status, code)
    assert MESSAGES.get(case, "") in response.json()["error"]["message"]


@pytest.mark.parametrize("case", sorted(PATH_CASES))
def test_bad_request_on_the_path_form_is_refused_and_changes_nothing(primed, case):
    status, code, path, request = PATH_CASES[case]
    primed[1].now += 1.0
    assert_refused_without_change(primed, primed[0].post(path, **request), status, code)


def test_wrong_size_message_names_the_accepted_sizes(primed):
    primed = primed[0]
    response = primed.post("/detect", json=body(image=b64png(np.zeros((64, 64), np.uint8))))
    assert "64x64" in response.json()["error"]["message"]
    assert "128x128 or 1152x1152" in response.json()["error"]["message"]


def test_streamed_body_over_the_limit_is_refused_without_content_length(primed):
    primed = primed[0]
    chunks = [b'{"stream_id": "s", "image": "'] + [b"A" * 50_000] * 6 + [b'"}']
    response = primed.post("/detect", content=iter(chunks), headers={"content-type": "application/json"})
    assert response.status_code == 413
    assert response.json()["error"]["code"] == "request_too_large"
    assert stream_state(primed, "s")["last_timestamp"] == 2.0


def test_delete_unknown_or_invalid_stream(primed):
    primed = primed[0]
    missing = primed.delete("/streams/never-seen")
    assert missing.status_code == 404 and missing.json()["error"]["code"] == "stream_not_found"
    too_long = primed.delete("/streams/" + "x" * 129)
    assert too_long.status_code == 422 and too_long.json()["error"]["code"] == "validation_error"
    assert stream_state(primed, "s")["frames_seen"] == 2
