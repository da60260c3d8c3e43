"""Liveness (the process answers) and readiness (model loaded and warmed up); never behind an API key.

Both run on the event loop with no thread-pool dependency, so they answer while every executor is busy.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends

from service.dependencies import get_service
from service.http.errors import error_responses
from service.pipeline.detector import DetectService
from service.schemas import Liveness, Readiness

router = APIRouter(prefix="/health", tags=["health"])


@router.get("/live", response_model=Liveness)
async def live() -> Liveness:
    return Liveness(status="alive")


@router.get("/ready", response_model=Readiness, responses=error_responses("ready"))
async def ready(service: DetectService = Depends(get_service)) -> Readiness:
    return Readiness(status="ready", model_version=service.runner.metadata.get("version", "unknown"))
