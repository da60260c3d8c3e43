"""Liveness (the process answers) and readiness (model loaded and warmed up)."""
from __future__ import annotations

from fastapi import APIRouter, Depends

from service.dependencies import get_service
from service.detector import DetectService
from service.schemas import ErrorResponse

router = APIRouter(prefix="/health", tags=["health"])


@router.get("/live")
async def live() -> dict[str, str]:
    return {"status": "alive"}


@router.get("/ready", responses={503: {"model": ErrorResponse, "description": "model loading or failed"}})
async def ready(service: DetectService = Depends(get_service)) -> dict[str, str]:
    return {"status": "ready", "model_version": service.runner.metadata.get("version", "unknown")}
