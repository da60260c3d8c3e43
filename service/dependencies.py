"""FastAPI dependencies: the loaded service (503 until the model is loaded and warmed up)."""
from __future__ import annotations

from fastapi import Request

from service.detector import DetectService
from service.errors import ApiError


def get_service(request: Request) -> DetectService:
    service = getattr(request.app.state, "service", None)
    if service is None:
        error = getattr(request.app.state, "load_error", None)
        reason = f"model failed to load: {error}" if error else "model is loading or warming up"
        raise ApiError(503, "not_ready", reason)
    return service
