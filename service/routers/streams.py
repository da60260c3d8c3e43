"""Stream inspection and reset: GET /streams, DELETE /streams/{stream_id}."""
from __future__ import annotations

import dataclasses

from fastapi import APIRouter, Depends, Path, Response

from service.dependencies import get_service
from service.detector import DetectService
from service.errors import ApiError
from service.schemas import STREAM_ID_PATTERN, ErrorResponse, StreamsResponse

router = APIRouter(prefix="/streams", tags=["streams"])


@router.get("", response_model=StreamsResponse)
async def list_streams(service: DetectService = Depends(get_service)) -> StreamsResponse:
    infos = service.store.snapshot()
    return StreamsResponse(
        count=len(infos),
        max_streams=service.store.max_streams,
        ttl_s=service.store.ttl_s,
        streams=[dataclasses.asdict(info) for info in infos],
    )


@router.delete("/{stream_id}", status_code=204, responses={404: {"model": ErrorResponse}})
async def delete_stream(
    stream_id: str = Path(min_length=1, max_length=128, pattern=STREAM_ID_PATTERN),
    service: DetectService = Depends(get_service),
) -> Response:
    """Forget a stream's buffer; its next frame starts a new one (this is also the reset)."""
    if not service.store.delete(stream_id):
        raise ApiError(404, "stream_not_found", f"no stream {stream_id!r} (never seen, deleted or expired)")
    return Response(status_code=204)
