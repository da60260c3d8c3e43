"""Parse POST /detect bodies: JSON (base64 image) or multipart/form-data (image file + form fields).

Multipart fields: stream_id, timestamp, optional pose_x, pose_y, pose_yaw (all three or none), and the
file field `image`. Unknown fields are refused (a typo like `pose_yw` must not silently drop the pose).
"""
from __future__ import annotations

from typing import Any

import orjson
from fastapi import Request
from pydantic import ValidationError
from starlette.datastructures import UploadFile

from service.errors import ApiError, format_validation_errors
from service.images import decode_base64
from service.schemas import DetectFields, DetectJson

JSON = "application/json"
MULTIPART = "multipart/form-data"
POSE_FORM_FIELDS = ("pose_x", "pose_y", "pose_yaw")
FORM_FIELDS = {"stream_id", "timestamp", "image", *POSE_FORM_FIELDS}


async def parse_detect_request(request: Request) -> tuple[DetectFields, bytes]:
    """-> (validated fields, raw image bytes); 400/415/422 with the reason on anything malformed."""
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media_type == JSON:
        return await _parse_json(request)
    if media_type == MULTIPART:
        return await _parse_multipart(request)
    raise ApiError(415, "unsupported_media_type",
                   f"Content-Type must be {JSON} or {MULTIPART}, got {media_type or 'none'!r}")


def _validate(model: type, data: Any) -> Any:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ApiError(422, "validation_error", format_validation_errors(exc.errors())) from exc


async def _parse_json(request: Request) -> tuple[DetectFields, bytes]:
    body = await request.body()
    if not body.strip():
        raise ApiError(400, "empty_body", "the request body is empty; expected a JSON object")
    try:
        data = orjson.loads(body)  # rejects NaN / Infinity literals, which Python's json would accept
    except orjson.JSONDecodeError as exc:
        raise ApiError(400, "invalid_json",
                       f"the body is not valid JSON (NaN and Infinity are not allowed): {exc}") from exc
    if not isinstance(data, dict):
        raise ApiError(422, "validation_error", f"expected a JSON object, got {type(data).__name__}")
    parsed = _validate(DetectJson, data)
    image = decode_base64(parsed.image)
    return DetectFields(stream_id=parsed.stream_id, timestamp=parsed.timestamp, pose=parsed.pose), image


async def _parse_multipart(request: Request) -> tuple[DetectFields, bytes]:
    async with request.form(max_files=1, max_fields=len(FORM_FIELDS)) as form:
        unknown = sorted(set(form.keys()) - FORM_FIELDS)
        if unknown:
            raise ApiError(422, "validation_error", f"unknown form fields {unknown}; allowed: {sorted(FORM_FIELDS)}")
        image = form.get("image")
        if not isinstance(image, UploadFile):
            raise ApiError(422, "validation_error", "form field 'image' must be a file (the PNG)")
        values = {key: form.get(key) for key in ("stream_id", "timestamp") if key in form}
        given = [key for key in POSE_FORM_FIELDS if key in form]
        if given and len(given) != len(POSE_FORM_FIELDS):
            raise ApiError(422, "validation_error",
                           f"pose form fields must come together: got {given}, need {list(POSE_FORM_FIELDS)}")
        if given:
            values["pose"] = {"x": form["pose_x"], "y": form["pose_y"], "yaw": form["pose_yaw"]}
        fields = _validate(DetectFields, values)
        return fields, await image.read()
