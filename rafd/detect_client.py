"""The client side of POST /detect, written once: the request a frame becomes, and sending it. Its stream ids follow
the rule the service checks (rafd.protocol: `stream_id_from`, `STREAM_ID_PATTERN`).

- The forms the project's clients post (`detect_request` of a body): JSON (`json_body`: the PNG as base64 text) and
  multipart/form-data (`multipart_body`: the PNG as the file field `image`); the stream named in the body, in the
  X-Stream-Id header or both; with or without a pose and previous_timestamp. A polar or native scan (Navtech_Polar,
  Oxford, Boreas) goes in either form as its PNG, unchanged: the service tells them apart by the image's shape.
  `flow=False` asks for an answer without the flow (`?flow=false`).
- Sending: `post` (urllib, a connection per request) or `exchange` (on a kept-alive `http.client` connection).

Standard library only, and opencv only inside `png_bytes`: `rafd client` needs no HTTP package. Not httpx: the load
benchmarks measure the service, not a client library (httpx adds about 1 ms per request).
"""

from __future__ import annotations

import base64
import http.client
import json
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

if TYPE_CHECKING:
    import numpy as np

# ------------------------------------------------------------------------------------------------ the request
JSON_TYPE = "application/json"
FORM_BOUNDARY = "rafd-detect-form-boundary"  # a PNG's compressed bytes hold this text only by a vanishing chance


@dataclass(frozen=True)
class FrameFields:
    """The fields of one frame besides its image, as posted."""

    timestamp: float
    stream_id: str | None = None  # None: the stream is named only in the X-Stream-Id header (or the path)
    pose: Sequence[float] | None = None  # (x, y, yaw) world pose; None: the service estimates ego motion
    # The stream's last frame the client got an answer for: a replica whose chain does not end there restarts it.
    previous_timestamp: float | None = None
    # A native scan's metres per range bin, as its sensor reported it (a ROS 2 bag's configuration): the service uses
    # it instead of the bin size of the dataset the scan's shape names.
    range_resolution_m: float | None = None

    def _given(self) -> dict[str, Any]:
        """stream_id, timestamp, previous_timestamp and range_resolution_m: those given, in both forms alike."""
        fields: dict[str, Any] = {} if self.stream_id is None else {"stream_id": self.stream_id}
        fields["timestamp"] = self.timestamp
        if self.previous_timestamp is not None:
            fields["previous_timestamp"] = self.previous_timestamp
        if self.range_resolution_m is not None:
            fields["range_resolution_m"] = self.range_resolution_m
        return fields

    def json_fields(self, image: str) -> dict[str, Any]:
        """The JSON body as a dict, `image` the base64 PNG text; values as given (tests post odd ones on purpose)."""
        fields = self._given() | {"image": image}
        if self.pose is not None:
            fields["pose"] = {"x": self.pose[0], "y": self.pose[1], "yaw": self.pose[2]}
        return fields

    def form_fields(self) -> dict[str, str]:
        """The multipart form's text fields; numbers written as JSON numbers (the service reads them so)."""
        fields = self._given()
        if self.pose is not None:
            fields |= {"pose_x": self.pose[0], "pose_y": self.pose[1], "pose_yaw": self.pose[2]}
        return {key: value if isinstance(value, str) else json.dumps(value) for key, value in fields.items()}


@dataclass(frozen=True)
class DetectRequest:
    """One POST /detect as it is sent."""

    path: str  # with its query
    body: bytes
    headers: dict[str, str]


def pose_of(row: Any) -> tuple[float, float, float]:
    """(x, y, yaw) as Python floats from a pose row (a numpy array's or a sequence's first three values)."""
    return float(row[0]), float(row[1]), float(row[2])


def png_bytes(image: np.ndarray) -> bytes:
    """A uint8 image as PNG bytes; ValueError when opencv cannot encode it."""
    import cv2  # here, not at the top: the load benchmarks and `rafd client --help` stay light

    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {image.shape} and dtype {image.dtype}")
    return encoded.tobytes()


def base64_png(png: bytes) -> str:
    """PNG bytes as the text of a JSON body's `image`."""
    return base64.b64encode(png).decode("ascii")


def api_key_header(api_key: str | None) -> dict[str, str]:
    """The X-API-Key header a service run with RAFD_API_KEYS checks; none without a key."""
    return {"X-API-Key": api_key} if api_key else {}


def stream_header(stream_id: str | None) -> dict[str, str]:
    """The stream named outside the body: routers that keep a stream on one replica hash on this header
    (deploy/nginx.conf, deploy/kubernetes/ingress.yaml), and the service takes the frame's place in the stream
    before its body is read."""
    return {} if stream_id is None else {"X-Stream-Id": stream_id}


def detect_path(flow: bool = True) -> str:
    """POST /detect's path; flow=False: the answer leaves the flow out (less to compute and to send)."""
    return "/detect" if flow else "/detect?flow=false"


@dataclass(frozen=True)
class Body:
    """A /detect body in one of its forms, with the media type that names the form."""

    content: bytes
    content_type: str


def json_body(fields: FrameFields, image: str) -> Body:
    """The JSON form: `image` the base64 PNG text (base64_png)."""
    return Body(json.dumps(fields.json_fields(image)).encode(), JSON_TYPE)


def multipart_body(fields: FrameFields, png: bytes) -> Body:
    """The multipart/form-data form: the PNG bytes as the file field `image`, the other fields as text."""
    parts = [
        f'--{FORM_BOUNDARY}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode()
        for name, value in fields.form_fields().items()
    ]
    parts.append(
        f'--{FORM_BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="scan.png"\r\n'
        "Content-Type: image/png\r\n\r\n".encode()
        + png
        + f"\r\n--{FORM_BOUNDARY}--\r\n".encode()
    )
    return Body(b"".join(parts), f"multipart/form-data; boundary={FORM_BOUNDARY}")


def detect_request(
    body: Body, *, flow: bool = True, header_stream_id: str | None = None, api_key: str | None = None
) -> DetectRequest:
    """POST /detect of `body`; `header_stream_id` names the stream in X-Stream-Id (the service requires it to equal
    the body's stream_id when both are given), `api_key` goes in X-API-Key."""
    headers = {"Content-Type": body.content_type, **api_key_header(api_key), **stream_header(header_stream_id)}
    return DetectRequest(detect_path(flow), body.content, headers)


# ------------------------------------------------------------------------------------------------ sending it
def post(url: str, request: DetectRequest, timeout: float) -> http.client.HTTPResponse:
    """POST `request` to the service at base URL `url` over urllib (a connection per request) -> the open answer
    (use it as a context manager). urllib's errors as urlopen raises them: HTTPError for a status of 400 or more,
    URLError when the service cannot be reached."""
    address = url.rstrip("/") + request.path
    prepared = urllib.request.Request(address, data=request.body, headers=request.headers, method="POST")
    return urllib.request.urlopen(prepared, timeout=timeout)


def connect(url: str, timeout: float) -> http.client.HTTPConnection:
    """A plain `http.client` connection to the service at `url` (127.0.0.1 when the URL names no host), for
    `exchange`: it stays open between requests (keep-alive), so latencies are the service's, not connecting's."""
    address = urlsplit(url)
    return http.client.HTTPConnection(address.hostname or "127.0.0.1", address.port, timeout=timeout)


def exchange(connection: http.client.HTTPConnection, request: DetectRequest) -> tuple[int, bytes]:
    """Send `request` on `connection` and read its whole answer -> (status, body); the connection stays open."""
    connection.request("POST", request.path, request.body, request.headers)
    response = connection.getresponse()
    return response.status, response.read()
