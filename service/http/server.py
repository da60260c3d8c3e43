"""How `rafd-serve` runs the app: one uvicorn process with the service's HTTP protocol and its limits.

- HTTP: uvicorn's httptools parser through `service.http.head_limits.LimitedHttpToolsProtocol`, which refuses a request
  line over RAFD_MAX_REQUEST_LINE_BYTES (414), more than RAFD_MAX_HEADERS header fields or RAFD_MAX_HEADER_BYTES of them
  (431), and a head slower than RAFD_HEADER_TIMEOUT_S (408) before the app sees the request. Chosen over uvicorn's
  h11 mode, which bounds the head's size but answers 400 and costs more per request (docs/archive.md, "Server
  overhead").
- Graceful shutdown: on SIGTERM the server stops accepting, lets requests in progress finish for at most
  RAFD_SHUTDOWN_TIMEOUT_S, then cancels what is left (a slow client cannot hold the exit).
- Keep-alive: idle connections stay open RAFD_KEEP_ALIVE_TIMEOUT_S (75 s), longer than a proxy's upstream keep-alive
  (nginx 60 s), so the proxy closes first and never reuses a connection the service is closing (docs/deployment.md).
- Proxy headers: uvicorn's defaults (X-Forwarded-For trusted from FORWARDED_ALLOW_IPS, 127.0.0.1 unless set).
"""

from __future__ import annotations

import asyncio
from typing import Any

import uvicorn
from fastapi import FastAPI

from service.http.head_limits import HeadLimits, limited_protocol
from service.settings import Settings


def head_limits(settings: Settings) -> HeadLimits:
    return HeadLimits(
        max_request_line_bytes=settings.max_request_line_bytes,
        max_headers=settings.max_headers,
        max_header_bytes=settings.max_header_bytes,
        header_timeout_s=settings.header_timeout_s,
    )


def http_protocol(app: FastAPI, settings: Settings) -> type[asyncio.Protocol]:
    """The protocol class, its refusals counted in the app's metrics (route "unmatched": no route was matched) and by
    the app's refusal penalty."""
    metrics = getattr(app.state, "metrics", None)
    return limited_protocol(
        head_limits(settings),
        metrics.refused_before_app if metrics is not None else None,
        getattr(app.state, "refusal_penalty", None),
    )


def uvicorn_options(app: FastAPI, settings: Settings) -> dict[str, Any]:
    """Options for uvicorn.run / uvicorn.Config beyond the address and the log level."""
    return {
        "http": http_protocol(app, settings),
        "timeout_graceful_shutdown": settings.shutdown_timeout_s,
        "timeout_keep_alive": settings.keep_alive_timeout_s,  # longer than the proxy's (RAFD_KEEP_ALIVE_TIMEOUT_S)
        "lifespan": "on",
    }


def server_config(app: FastAPI, settings: Settings, host: str, port: int, log_level: str = "info") -> uvicorn.Config:
    """The uvicorn configuration `serve` runs (tests start the same server in a thread)."""
    return uvicorn.Config(app, host=host, port=port, log_level=log_level, **uvicorn_options(app, settings))


def serve(app: FastAPI, settings: Settings, host: str, port: int, log_level: str = "info") -> None:
    """Serve until SIGINT / SIGTERM."""
    uvicorn.run(app, host=host, port=port, log_level=log_level, **uvicorn_options(app, settings))
