"""Requests that two parsers could read differently are refused, not guessed (issue 40, finding 6): two Content-Type
headers (the first was used), two `boundary=` parameters (the last won), and `DELETE /streams/` (a 307 redirect to
GET's `/streams`, no JSON) is a 404 JSON error."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.utils.service_testing import blob_frame, detect_json, png, stream_state

FRAME = blob_frame(128, [(8, 8, 255)])


def form_body(boundary: bytes) -> bytes:
    parts = [
        b"--" + boundary + b'\r\nContent-Disposition: form-data; name="stream_id"\r\n\r\nm\r\n',
        b"--" + boundary + b'\r\nContent-Disposition: form-data; name="timestamp"\r\n\r\n1\r\n',
        b"--" + boundary + b'\r\nContent-Disposition: form-data; name="image"; filename="f.png"\r\n'
        b"Content-Type: image/png\r\n\r\n" + png(FRAME) + b"\r\n",
        b"--" + boundary + b"--\r\n",
    ]
    return b"".join(parts)


def test_two_content_type_headers_are_400(client: TestClient):
    import json

    body = json.dumps(detect_json("c", 1.0, FRAME)).encode()
    for pair in (("application/json", "multipart/form-data; boundary=x"), ("application/json", "application/json")):
        response = client.post("/detect", content=body, headers=[("content-type", pair[0]), ("content-type", pair[1])])
        assert response.status_code == 400, response.text
        assert response.json()["error"]["code"] == "ambiguous_content_type"
    assert stream_state(client, "c") is None
    assert client.post("/detect", content=body, headers={"content-type": "application/json"}).status_code == 200


def test_two_boundary_parameters_are_400(client: TestClient):
    body = form_body(b"second")
    for content_type in (
        "multipart/form-data; boundary=first; boundary=second",
        'multipart/form-data; boundary="second"; BOUNDARY=first',
    ):
        response = client.post("/detect", content=body, headers={"content-type": content_type})
        assert response.status_code == 400, response.text
        assert response.json()["error"]["code"] == "invalid_multipart"
        assert "more than one boundary" in response.json()["error"]["message"]
    accepted = client.post("/detect", content=body, headers={"content-type": "multipart/form-data; boundary=second"})
    assert accepted.status_code == 200, accepted.text


def test_a_trailing_slash_is_not_redirected(client: TestClient):
    for method in ("DELETE", "GET", "POST"):
        response = client.request(method, "/streams/", follow_redirects=False)
        assert response.status_code in (404, 405), (method, response.status_code)
        assert response.json()["error"]["code"] in ("not_found", "method_not_allowed")
        assert "location" not in response.headers
    assert client.get("/streams").status_code == 200
