"""The FastAPI app factory: `uvicorn --factory service.app:create_app`.

The model is loaded in the lifespan, in a background task, never at import: /health/live answers at
once, /health/ready (and every model route) answers 503 until the model is loaded and warmed up.
The interactive API pages (/docs, /redoc) load their assets from this process (/static-offline-docs/), not from
the internet. Middleware, outermost first: metrics (counts every answer, 401s and 413s included), intake (arrival
stamp, the per-client request limit and the minimum body rate: service/http/intake.py), API keys (401 before anything is
read), the body size limit (413), then the routes. The HTTP server limits each request head before any of them
(service/http/head_limits.py, run by service/http/server.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

import cv2
from fastapi import FastAPI
from fastapi_offline import FastAPIOffline
from starlette.concurrency import run_in_threadpool

from rafd import __version__
from service.http.auth import OPEN_PATHS, ApiKeyMiddleware, load_api_keys
from service.http.body_limit import BodySizeLimitMiddleware
from service.http.errors import ANY, ERRORS, error_responses, install_error_handlers, route_codes
from service.http.intake import IntakeMiddleware
from service.http.penalty import RefusalPenalty
from service.loading import check_buffer_length, open_runner, warm_up
from service.pipeline.detector import DetectService, Executors
from service.pipeline.live import LiveView
from service.pipeline.poses import Odometry
from service.pipeline.service_metrics import MetricsMiddleware, ServiceMetrics
from service.pipeline.streams import StreamStore
from service.routers import detect, health, metrics, model, streams

if TYPE_CHECKING:
    from rafd.runtime import Runner
from service.settings import Settings, get_settings

log = logging.getLogger(__name__)

# Errors any route can answer, before or besides its own (each route's responses list the rest).
ANY_ROUTE_ERRORS = (
    'Every error is `{"error": {"code", "message"}}`. Besides each route\'s own errors, any route may answer: '
    + "; ".join(f"{ERRORS[code].status} `{code}`: {ERRORS[code].meaning}" for code in route_codes(ANY))
    + "."
)


def create_app(
    settings: Settings | None = None,
    runner: Runner | None = None,
    odometry: Odometry | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> FastAPI:
    """Build the app; `runner` (any rafd.runtime.Runner) and `odometry` can be injected for tests.

    Raises ValueError at once when the configured API keys are malformed or their file cannot be read.
    """
    settings = settings or get_settings()
    service_metrics = ServiceMetrics()
    api_keys = load_api_keys(settings)
    # ValueError naming the extra when foxglove is absent, or when keys are configured and the view names none
    live = LiveView.from_settings(settings, service_metrics, tuple(name for name, _ in api_keys.keys))

    async def load(app: FastAPI) -> None:
        try:
            loaded = runner if runner is not None else await run_in_threadpool(open_runner, settings)
            check_buffer_length(settings, loaded)
            await run_in_threadpool(warm_up, loaded, settings)
            store = StreamStore(
                settings.max_streams,
                settings.stream_ttl_s,
                clock=clock,
                on_evict=lambda reason: service_metrics.evictions.labels(reason=reason).inc(),
                queue_limit=settings.stream_queue_limit,
                retry_after_s=settings.retry_after_s,
                max_streams_per_key=streams_per_key(settings, api_keys.count),
                on_restart=lambda reason: service_metrics.restarts.labels(reason=reason).inc(),
            )
            service_metrics.track_active_streams(lambda: len(store))
            # Decode and odometry jobs get their parallelism from their executors (one thread each by default);
            # opencv's own thread pool inside a job would compete with the model's threads for the same cores.
            # One thread costs a lone stream's odometry 6-11% (docs/archive.md, "Odometry").
            cv2.setNumThreads(1)
            app.state.service = DetectService(
                loaded, settings, store, service_metrics, odometry, Executors.from_settings(settings, service_metrics)
            )
            if live is not None:
                live.resolution = loaded.config.resolution
                app.state.service.on_answer = live.offer
            log.info("model ready: %s", loaded.metadata.get("version", "unknown"))
        except Exception as exc:  # readiness reports it; the process stays up for inspection
            log.exception("model failed to load")
            app.state.load_error = f"{type(exc).__name__}: {exc}"

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.service = None
        app.state.load_error = None
        if live is not None:
            live.start()
        task = asyncio.create_task(load(app))
        try:
            yield
        finally:
            if live is not None:
                live.stop()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            if app.state.service is not None:
                app.state.service.executors.shutdown()
            app.state.service = None

    # /docs (Swagger UI) and /redoc with their JavaScript and CSS served by this process (fastapi-offline ships them,
    # under /static-offline-docs/), never from a CDN: the pages work on a network without internet.
    # redirect_slashes off: `DELETE /streams/` answered a 307 to GET's `/streams` (a redirect a client may follow with
    # another method, and no JSON error); a path no route has is 404 `not_found`, with or without a trailing slash.
    app = FastAPIOffline(
        title="RaFD radar detection service",
        version=__version__,
        lifespan=lifespan,
        description=ANY_ROUTE_ERRORS,
        redirect_slashes=False,
    )
    app.state.settings = settings
    app.state.live = live
    app.state.refusal_penalty = RefusalPenalty(settings.refusal_penalty_s, settings.refusal_penalty_after)
    app.state.metrics = service_metrics
    app.state.service = None
    app.state.load_error = None
    install_error_handlers(app)
    for router in (detect.router, streams.router, health.router, metrics.router):
        app.include_router(router)
    app.include_router(model.router, responses=error_responses("model"))
    # Last added = outermost: metrics also count the 401s, 413s and 429s answered before the routes.
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_request_bytes)
    app.add_middleware(ApiKeyMiddleware, keys=api_keys)
    app.add_middleware(
        IntakeMiddleware,
        max_per_client=settings.max_requests_per_client,
        min_rate=settings.min_body_bytes_per_s,
        grace_s=settings.body_rate_grace_s,
        retry_after_s=settings.retry_after_s,
    )
    app.add_middleware(MetricsMiddleware, metrics=service_metrics)
    if api_keys.enabled:
        _document_api_keys(app)
    return app


def streams_per_key(settings: Settings, keys: int) -> int:
    """RAFD_MAX_STREAMS_PER_KEY, or an equal share of RAFD_MAX_STREAMS per configured key (all of it without keys)."""
    if keys == 0:
        return settings.max_streams
    return settings.max_streams_per_key or max(1, settings.max_streams // keys)


def _document_api_keys(app: FastAPI) -> None:
    """OpenAPI: the two ways to present a key, required on every operation but liveness and readiness."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = build()
        schema.setdefault("components", {})["securitySchemes"] = {
            "ApiKeyHeader": {"type": "apiKey", "in": "header", "name": "X-API-Key"},
            "BearerAuth": {"type": "http", "scheme": "bearer"},
        }
        for path, operations in schema["paths"].items():
            for operation in operations.values():
                operation["security"] = [] if path in OPEN_PATHS else [{"ApiKeyHeader": []}, {"BearerAuth": []}]
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
