"""POST /detect and POST /streams/{stream_id}/detect: one radar frame of one stream -> oriented boxes and BEV flow.

The stream may be named outside the body (the `X-Stream-Id` header, or the path form) so that a load balancer
can route on it without reading the body, and so that the frame's place in its stream's queue is taken before
its body is read. Every id given (header, path, body) must be the same (else 422 `stream_id_mismatch`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from fastapi import APIRouter, Depends, Header, Path, Query, Request, Response

from service.body.form import multipart_schema
from service.dependencies import get_caller, get_service
from service.http.errors import ApiError, error_responses
from service.pipeline.detector import DetectOptions, DetectService
from service.schemas import STREAM_ID_MAX_LENGTH, STREAM_ID_PATTERN, DetectJson, DetectResponse

router = APIRouter(tags=["detect"])

_REQUEST_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": DetectJson.model_json_schema(ref_template="#/components/schemas/{model}")},
            "multipart/form-data": {"schema": multipart_schema()},
        },
    }
}
_RESPONSES = {200: {"model": DetectResponse}, **error_responses("detect")}


@dataclass(frozen=True)
class DetectCall:
    """What both detect routes take besides the body: options, the X-Stream-Id header, the service, the caller."""

    options: DetectOptions
    header_stream_id: str | None
    service: DetectService
    caller: str | None

    async def answer(self, request: Request, stream_hint: str | None) -> Response:
        answer = await self.service.detect(request, stream_hint, self.caller, self.options)
        return Response(answer.to_json(), media_type="application/json")


async def detect_call(
    flow: bool = Query(True, description="false leaves the flow field out"),
    flow_format: Literal["list", "base64", "png"] = Query(
        "list",
        description="list: nested [2][Hf][Wf] metres rounded to 1 mm (validity: [Hf][Wf], rounded down to 0.01); "
        "base64: little-endian float16 bytes, row-major [2, Hf, Wf] (validity: [Hf, Wf]); png: a base64 16-bit "
        "greyscale PNG of [2 Hf, Wf], the x rows over the y rows, millimetres + 32768 (validity: an 8-bit PNG of "
        "[Hf, Wf], k for k / 100). A whole 1152 px scan's flow is 288 x 288 cells: about 1.3 MB of JSON as a list, "
        "0.66 MB as base64, 0.25 MB as png",
    ),
    x_stream_id: str | None = Header(
        default=None,
        alias="X-Stream-Id",
        min_length=1,
        max_length=STREAM_ID_MAX_LENGTH,
        pattern=STREAM_ID_PATTERN,
        description="the stream, named outside the body (route on it; must equal the body's stream_id when both "
        "are given)",
    ),
    service: DetectService = Depends(get_service),
    caller: str | None = Depends(get_caller),
) -> DetectCall:
    return DetectCall(DetectOptions(flow=flow, flow_format=flow_format), x_stream_id, service, caller)


@router.post("/detect", responses=_RESPONSES, openapi_extra=_REQUEST_BODY)
async def detect(request: Request, call: DetectCall = Depends(detect_call)) -> Response:
    return await call.answer(request, call.header_stream_id)


@router.post("/streams/{stream_id}/detect", responses=_RESPONSES, openapi_extra=_REQUEST_BODY)
async def detect_on_stream(
    request: Request,
    stream_id: str = Path(min_length=1, max_length=STREAM_ID_MAX_LENGTH, pattern=STREAM_ID_PATTERN),
    call: DetectCall = Depends(detect_call),
) -> Response:
    """The same as POST /detect with the stream named in the path."""
    if call.header_stream_id is not None and call.header_stream_id != stream_id:
        raise ApiError(
            "stream_id_mismatch",
            f"the X-Stream-Id header {call.header_stream_id!r} differs from the path's stream id {stream_id!r}",
        )
    return await call.answer(request, stream_id)
