"""Prometheus metrics on a per-app registry (two apps in one process, e.g. tests, never share counters).

Every label comes from a closed set: the route TEMPLATE (never the raw path: stream ids would explode it) or
"unmatched", a known HTTP method or "other" (a client can send any token as a method), a status the service
answers or "other". So no request, however made up, adds a series. Every route is counted under its own template,
also the documentation's (/docs, /redoc, /openapi.json: plain Starlette routes, which FastAPI does not mark in the
scope) and also when a middleware answered before routing (401, 429, 413); "unmatched" is a path no route has. Heads
refused by the HTTP server before the app (414, 431, 408: service/http/head_limits.py) count as "unmatched", "other".
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from starlette.routing import Mount, Route, compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.http.errors import CLIENT_CLOSED_REQUEST, ERRORS

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "PATCH"})
STATUSES = frozenset({200, 204, CLIENT_CLOSED_REQUEST} | {error.status for error in ERRORS.values()})
EXECUTORS = ("parse", "decode", "odometry", "model")
RESTART_REASONS = ("evicted", "expired", "gap", "previous_timestamp_mismatch", "view_changed")


def method_label(method: str) -> str:
    return method if method in METHODS else "other"


def status_label(status: int) -> str:
    return str(status) if status in STATUSES else "other"


class RouteLabels:
    """Route templates for requests FastAPI did not mark with their route: its documentation's plain routes, and any
    route when a middleware answered before routing. Built once, from the app's plain routes and the OpenAPI
    document's path templates (public interfaces only: FastAPI's own route objects change between versions)."""

    def __init__(self) -> None:
        self._table: list[tuple[re.Pattern[str], str]] | None = None

    def label(self, scope: Scope) -> str:
        path = getattr(scope.get("route"), "path", None)
        if path:
            return str(path)
        app = scope.get("app")
        if app is None:
            return "unmatched"
        if self._table is None:
            self._table = self._build(app)
        route_path = scope["path"][len(scope.get("root_path", "")) :] if scope.get("root_path") else scope["path"]
        for regex, template in self._table:
            if regex.match(route_path):
                return template
        return "unmatched"

    @staticmethod
    def _build(app: Any) -> list[tuple[re.Pattern[str], str]]:
        table = [(route.path_regex, route.path) for route in app.router.routes if isinstance(route, (Route, Mount))]
        openapi = getattr(app, "openapi", None)
        for template in openapi()["paths"] if callable(openapi) else ():
            table.append((compile_path(template)[0], template))
        return table


class ServiceMetrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(
            "rafd_requests",
            "HTTP requests by route, method and status code (499: the client left before its answer)",
            ["route", "method", "code"],
            registry=self.registry,
        )
        self.errors = Counter(
            "rafd_request_errors",
            "HTTP responses with status >= 400 by route and code",
            ["route", "code"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "rafd_request_duration_seconds",
            "HTTP request latency by route",
            ["route"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.model_latency = Histogram(
            "rafd_model_step_seconds",
            "onnxruntime time per detect step",
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.frames = Counter("rafd_frames_processed", "frames run through the model", registry=self.registry)
        self.active_streams = Gauge("rafd_active_streams", "streams holding a buffer", registry=self.registry)
        self.evictions = Counter(
            "rafd_stream_evictions", "streams evicted, by reason (ttl or lru)", ["reason"], registry=self.registry
        )
        self.queued = Gauge(
            "rafd_executor_queued", "jobs waiting for a worker, by executor", ["executor"], registry=self.registry
        )
        self.refused = Counter(
            "rafd_executor_refused",
            "jobs refused with 503 because the executor's queue was full, by executor",
            ["executor"],
            registry=self.registry,
        )
        self.restarts = Counter(
            "rafd_stream_restarts",
            "frames answered with stream_restarted: the first accepted frame of a stream id whose previous chain the "
            "service ended, by reason (evicted, expired; gap, previous_timestamp_mismatch: a frame that showed the "
            "chain held here stale or not its own)",
            ["reason"],
            registry=self.registry,
        )
        for reason in ("ttl", "lru"):
            self.evictions.labels(reason=reason)  # export zeros so dashboards see the series from the start
        for reason in RESTART_REASONS:
            self.restarts.labels(reason=reason)
        for executor in EXECUTORS:
            self.refused.labels(executor=executor)

    def track_active_streams(self, count: Callable[[], int]) -> None:
        """The gauge reads the store at scrape time (so TTL expiry shows without a background task)."""
        self.active_streams.set_function(count)

    def track_executor(self, name: str, waiting: Callable[[], int]) -> None:
        self.queued.labels(executor=name).set_function(waiting)

    def executor_refused(self, name: str) -> None:
        self.refused.labels(executor=name).inc()

    def refused_before_app(self, status: int) -> None:
        """A request head the HTTP server refused (service/http/head_limits.py): no route, no method known to count."""
        code = status_label(status)
        self.requests.labels(route="unmatched", method="other", code=code).inc()
        self.errors.labels(route="unmatched", code=code).inc()


class MetricsMiddleware:
    """Counts every HTTP request by its route template, method and status, all from closed sets."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app = app
        self.metrics = metrics
        self.routes = RouteLabels()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            path = self.routes.label(scope)
            code = status_label(status)
            self.metrics.requests.labels(route=path, method=method_label(scope["method"]), code=code).inc()
            if status >= 400:
                self.metrics.errors.labels(route=path, code=code).inc()
            self.metrics.latency.labels(route=path).observe(time.perf_counter() - start)
