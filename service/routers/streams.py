"""Stream inspection and reset: GET /streams, DELETE /streams/{stream_id} (in the caller's own namespace)."""

from __future__ import annotations

import dataclasses

from fastapi import APIRouter, Depends, Path, Response

from service.dependencies import get_caller, get_service
from service.http.errors import ApiError, error_responses
from service.pipeline.detector import DetectService
from service.schemas import STREAM_ID_MAX_LENGTH, STREAM_ID_PATTERN, StreamOut, StreamsResponse

router = APIRouter(prefix="/streams", tags=["streams"])


@router.get("", response_model=StreamsResponse, responses=error_responses("list_streams"))
async def list_streams(
    service: DetectService = Depends(get_service), caller: str | None = Depends(get_caller)
) -> StreamsResponse:
    """The caller's live streams (every stream when the service runs without API keys), least recently used first."""
    infos = service.store.snapshot(owner=caller)
    return StreamsResponse(
        count=len(infos),
        max_streams=service.store.max_streams,
        max_streams_per_key=service.store.max_streams_per_key,
        ttl_s=service.store.ttl_s,
        streams=[StreamOut.model_validate(dataclasses.asdict(info)) for info in infos],
    )


@router.delete(
    "/{stream_id}",
    status_code=204,
    responses=error_responses("delete_stream"),
)
async def delete_stream(
    stream_id: str = Path(min_length=1, max_length=STREAM_ID_MAX_LENGTH, pattern=STREAM_ID_PATTERN),
    service: DetectService = Depends(get_service),
    caller: str | None = Depends(get_caller),
) -> Response:
    """Forget a stream's buffer; its next frame starts a new chain (this is also the reset). Frames of the old
    chain still queued or running are refused with 409 `stream_reset`, a stream's first frame in flight included
    (204 then, though the stream had no accepted frame yet); 404 when the caller has no such stream: none accepted
    and none in flight."""
    if not service.store.delete(stream_id, owner=caller):
        raise ApiError("stream_not_found", f"no stream {stream_id!r} (never seen, deleted or expired)")
    return Response(status_code=204)
