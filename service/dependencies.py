"""FastAPI dependencies: the loaded service (503 until the model is loaded and warmed up) and the caller's key.

Both are `async def`: a plain `def` dependency runs on the shared thread pool, and readiness must never wait
behind work queued there.
"""

from __future__ import annotations

from fastapi import Request

from service.http.auth import caller_of
from service.http.errors import ApiError
from service.pipeline.detector import DetectService


async def get_service(request: Request) -> DetectService:
    service: DetectService | None = getattr(request.app.state, "service", None)
    if service is None:
        error = getattr(request.app.state, "load_error", None)
        reason = f"model failed to load: {error}" if error else "model is loading or warming up"
        raise ApiError("not_ready", reason)
    return service


async def get_caller(request: Request) -> str | None:
    """Name of the API key the request carried (None when the service runs without keys)."""
    return caller_of(request.scope)
