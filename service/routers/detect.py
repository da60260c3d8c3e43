"""POST /detect: one radar frame of one stream -> oriented boxes and the BEV flow field."""
from __future__ import annotations

from typing import Literal

import orjson
from fastapi import APIRouter, Depends, Query, Request, Response

from service.detector import DetectOptions, DetectService
from service.dependencies import get_service
from service.requests import parse_detect_request
from service.schemas import DetectFields, DetectJson, DetectResponse, ErrorResponse

router = APIRouter(tags=["detect"])

_MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["stream_id", "timestamp", "image"],
    "properties": {
        "stream_id": {"type": "string"},
        "timestamp": {"type": "number"},
        "pose_x": {"type": "number"},
        "pose_y": {"type": "number"},
        "pose_yaw": {"type": "number"},
        "image": {"type": "string", "format": "binary"},
    },
}

_ERRORS = {code: {"model": ErrorResponse} for code in (400, 409, 413, 415, 422, 503)}


@router.post(
    "/detect",
    responses={200: {"model": DetectResponse}, **_ERRORS},
    openapi_extra={"requestBody": {"required": True, "content": {
        "application/json": {"schema": DetectJson.model_json_schema(ref_template="#/components/schemas/{model}")},
        "multipart/form-data": {"schema": _MULTIPART_SCHEMA},
    }}},
)
async def detect(
    request: Request,
    flow: bool = Query(True, description="false leaves the flow field out"),
    flow_format: Literal["list", "base64"] = Query(
        "list", description="list: nested [2][Hf][Wf] metres rounded to 1 mm; "
                            "base64: little-endian float16 bytes, row-major [2, Hf, Wf]"),
    service: DetectService = Depends(get_service),
) -> Response:
    fields: DetectFields
    fields, image = await parse_detect_request(request)
    answer = await service.detect(fields, image, DetectOptions(flow=flow, flow_format=flow_format))
    return Response(orjson.dumps(answer), media_type="application/json")
