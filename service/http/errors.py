"""One error shape for every 4xx/5xx: {"error": {"code": str, "message": str}}, from one registry of codes.

Every code the service can answer is in `ERRORS`, one table (status, meaning, the routes answering it); `ApiError`
only takes a registered code, and the OpenAPI responses of each route (`error_responses`) and docs/api.md's table
(`error_table`) are made from it. Messages are capped (`MAX_MESSAGE_CHARS`) so an error never grows with the input.
Middleware that refuses before any route runs answers the same shape with `send_refusal`. A client is known by its
address (`client_of`), which the refusal penalty and the per-client limits count.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import orjson
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.responses import Response
from starlette.types import Scope, Send

log = logging.getLogger(__name__)

# An error message is for a human: a few hundred characters say what was wrong; more only echoes the input.
MAX_MESSAGE_CHARS = 512
# Pydantic reports one error per bad field or extra key; a few name the problem.
MAX_LISTED_ERRORS = 5
MAX_LOCATION_CHARS = 64
# Not an answer anyone receives: the client left before its answer. Counted under this status in the metrics
# (nginx's convention), never as a 500.
CLIENT_CLOSED_REQUEST = 499


@dataclass(frozen=True)
class ErrorCode:
    status: int
    meaning: str  # what docs/api.md's table and the OpenAPI responses say of it
    routes: frozenset[str]  # the routes answering it (ROUTES), or {ANY}: any route may (before or besides its own)


ANY = "any"
ROUTES = ("detect", "list_streams", "delete_stream", "model", "metrics", "ready")
_MODEL = frozenset({"detect", "list_streams", "delete_stream", "model", "ready"})  # the routes that need the model
_PROTECTED = frozenset({"detect", "list_streams", "delete_stream", "model", "metrics"})  # behind the API keys
_DETECT = frozenset({"detect"})
_ANY = frozenset({ANY})

# The one table of the codes: status, meaning and routes. The OpenAPI responses of each route (error_responses) and
# the table of docs/api.md (`python -m tools.api_tables --write`, checked by a test) are made from it.
ERRORS: Mapping[str, ErrorCode] = {
    "empty_body": ErrorCode(400, "the body is empty", _DETECT),
    "invalid_json": ErrorCode(
        400,
        "not valid JSON (strict UTF-8, no byte-order mark, nothing after the value), including NaN, Infinity and "
        "numbers out of a double's range (`1e400`, an integer of 400 digits)",
        _DETECT,
    ),
    "invalid_multipart": ErrorCode(
        400,
        "the multipart body cannot be parsed: no boundary or more than one `boundary=` parameter, malformed or "
        "nameless parts, no closing boundary",
        _DETECT,
    ),
    "ambiguous_content_type": ErrorCode(
        400,
        "the request carries more than one `Content-Type` header (another parser could have read the other one)",
        _DETECT,
    ),
    "missing_api_key": ErrorCode(
        401,
        "API keys are configured and the request carries none (neither `X-API-Key` nor `Authorization: Bearer`; "
        "`WWW-Authenticate: Bearer`)",
        _ANY | _PROTECTED,
    ),
    "invalid_api_key": ErrorCode(
        401,
        "API keys are configured and the request's key is not one of them (`WWW-Authenticate: Bearer`); the message "
        "says nothing about which keys exist",
        _ANY | _PROTECTED,
    ),
    "not_found": ErrorCode(
        404, "no such route (a trailing slash is not redirected: `DELETE /streams/` is 404, not a 307)", _ANY
    ),
    "stream_not_found": ErrorCode(
        404,
        "DELETE of a stream this key has not (never seen, deleted or expired; no frame of it accepted or in flight)",
        frozenset({"delete_stream"}),
    ),
    "method_not_allowed": ErrorCode(405, "the route does not take this method", _ANY),
    "body_timeout": ErrorCode(
        408,
        "the body did not arrive within `RAFD_BODY_TIMEOUT_S` (the frame held its stream's place meanwhile)",
        _DETECT,
    ),
    "body_too_slow": ErrorCode(
        408,
        "after its first `RAFD_BODY_RATE_GRACE_S` (1 s) the body fell behind `RAFD_MIN_BODY_BYTES_PER_S` (64 KiB/s) on "
        "average since the request arrived; the connection is closed",
        _ANY | _DETECT,
    ),
    "request_header_timeout": ErrorCode(
        408,
        "the request line and headers did not arrive within `RAFD_HEADER_TIMEOUT_S` (10 s) of the connection (or of "
        "the request's first byte on a kept-alive connection); answered by the HTTP server, the connection closed",
        _ANY,
    ),
    "timestamp_not_increasing": ErrorCode(
        409,
        "not after the stream's last accepted frame, or after an earlier-arrived queued frame; or the last accepted "
        "frame's timestamp with another image or pose (the same frame again is answered again)",
        _DETECT,
    ),
    "pose_source_conflict": ErrorCode(409, "a request pose on a stream started without poses", _DETECT),
    "stream_reset": ErrorCode(
        409,
        "the stream was deleted while this frame waited or ran: the frame belonged to the ended chain and was not "
        "used; send it again to start the new chain",
        _DETECT,
    ),
    "request_too_large": ErrorCode(
        413,
        "body over `RAFD_MAX_REQUEST_BYTES` (from Content-Length, and again while it streams)",
        _ANY | _DETECT,
    ),
    "request_line_too_long": ErrorCode(
        414,
        "the request line over `RAFD_MAX_REQUEST_LINE_BYTES` (8 KiB); answered by the HTTP server, the connection "
        "closed",
        _ANY,
    ),
    "unsupported_media_type": ErrorCode(415, "neither `application/json` nor `multipart/form-data`", _DETECT),
    "validation_error": ErrorCode(
        422,
        "a field missing, unknown, duplicated, of the wrong type or out of range; a bad path, query or header value; "
        "no stream id anywhere; a JSON body with more structure than a detect request can have "
        "([Limits](#limits)), refused unparsed",
        frozenset({"detect", "delete_stream"}),
    ),
    "stream_id_mismatch": ErrorCode(422, "the body's `stream_id`, `X-Stream-Id` and the path disagree", _DETECT),
    "invalid_image": ErrorCode(
        422,
        "not base64 / not a PNG / truncated or corrupt, or refused by the chunk check (too many or too large "
        "ancillary chunks, image data inflating past its header's size, bytes after IEND, ...)",
        _DETECT,
    ),
    "timestamp_gap_too_small": ErrorCode(
        422,
        "the frame follows the stream's last accepted frame by less than `RAFD_MIN_FRAME_GAP_S` (0.01 s; rule "
        "`min_frame_gap`); the stream is unchanged",
        _DETECT,
    ),
    "implausible_motion": ErrorCode(
        422,
        "the frame's pose (the request's or odometry's) moved faster than `RAFD_MAX_SPEED_MPS` (70 m/s) since the "
        "stream's last accepted frame (rule `max_speed`); the frame is refused and the stream keeps its last pose",
        _DETECT,
    ),
    "unsupported_image_size": ErrorCode(
        422,
        "not one of the accepted square sizes nor the polar scan's 400x576 nor a native scan's accepted shape (the "
        "message names them)",
        _DETECT,
    ),
    "unsupported_image_format": ErrorCode(
        422, "not 8-bit greyscale (e.g. 1-bit, 16-bit, RGB, palette, alpha)", _DETECT
    ),
    "stream_queue_full": ErrorCode(429, "`RAFD_STREAM_QUEUE_LIMIT` frames of this stream are already queued", _DETECT),
    "too_many_client_requests": ErrorCode(
        429,
        "the client (by address) already has `RAFD_MAX_REQUESTS_PER_CLIENT` (16) unfinished requests; any route but "
        "the health probes, before the API key is checked",
        _ANY | _PROTECTED,
    ),
    "request_header_too_large": ErrorCode(
        431,
        "more than `RAFD_MAX_HEADERS` (100) header fields or more than `RAFD_MAX_HEADER_BYTES` (32 KiB) of them; "
        "answered by the HTTP server, the connection closed",
        _ANY,
    ),
    "internal_error": ErrorCode(
        500,
        "the model or the service failed; no stream changed",
        _ANY | _DETECT,
    ),
    "odometry_failed": ErrorCode(500, "odometry gave no finite motion; no stream changed", _DETECT),
    "not_ready": ErrorCode(
        503, "the model is loading or warming up, or failed to load (the message says which)", _MODEL
    ),
    "overloaded": ErrorCode(
        503,
        "`RAFD_MAX_RECEIVING_REQUESTS` requests receiving their body (refused before the body is read), "
        "`RAFD_MAX_INFLIGHT_REQUESTS` requests whose body has arrived, or the parse / decode / odometry / model "
        "queue is full; retry after the Retry-After header's seconds",
        _DETECT,
    ),
    "odometry_unavailable": ErrorCode(503, "this build cannot estimate ego motion: send poses", _DETECT),
    "http_error": ErrorCode(
        400, "any other refusal by the HTTP framework (not expected; listed so every code is documented)", _ANY
    ),
}


class ApiError(Exception):
    """A request the service refuses, with a registered code and a human-readable reason."""

    def __init__(self, code: str, message: str, headers: Mapping[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = ERRORS[code].status  # KeyError: every code must be registered (and so documented)
        self.code = code
        self.message = message
        self.headers = dict(headers or {})


def timestamp_error(stream_id: str, reason: str) -> ApiError:
    """409 timestamp_not_increasing naming the stream and the two ways out (a second run of the same frames, e.g.
    `rafd client` again with the same --stream-id, lands here)."""
    return ApiError(
        "timestamp_not_increasing",
        f"stream {stream_id!r}: {reason}; timestamps must increase in arrival order within a stream. To send these "
        f"frames again, start the stream over with DELETE /streams/{stream_id} (rafd client --reset), or post them "
        "to a new stream id",
    )


def cap_message(message: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    return message if len(message) <= limit else message[: limit - 15] + " ... (truncated)"


def error_body(code: str, message: str) -> dict[str, Any]:
    return {"error": {"code": code, "message": cap_message(message)}}


def error_response(status: int, code: str, message: str, headers: Mapping[str, str] | None = None) -> JSONResponse:
    return JSONResponse(error_body(code, message), status_code=status, headers=dict(headers or {}))


async def send_refusal(
    send: Send, code: str, message: str, headers: Mapping[str, str] | None = None, close: bool = False
) -> None:
    """Answer a refusal straight on the ASGI `send`, for middleware that refuses before any route runs: the
    registered code's status and the one error shape. `close`: say `Connection: close` (the request's body is not
    read, so the connection cannot carry another request)."""
    body = orjson.dumps(error_body(code, message))
    fields = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    fields += [(name.lower().encode("latin-1"), value.encode("latin-1")) for name, value in (headers or {}).items()]
    if close:
        fields.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": ERRORS[code].status, "headers": fields})
    await send({"type": "http.response.body", "body": body})


def format_validation_errors(errors: Sequence[Mapping[str, Any]]) -> str:
    """Pydantic errors -> one short line: `field.path: reason; ...` (at most MAX_LISTED_ERRORS, names capped)."""
    parts = []
    for error in errors[:MAX_LISTED_ERRORS]:
        location = ".".join(
            str(p)[:MAX_LOCATION_CHARS] for p in error.get("loc", ()) if p not in ("body", "query", "path", "header")
        )
        parts.append(f"{location or 'request'}: {error.get('msg', 'invalid')}")
    if len(errors) > MAX_LISTED_ERRORS:
        parts.append(f"and {len(errors) - MAX_LISTED_ERRORS} more")
    return "; ".join(parts)


def route_codes(route: str) -> list[str]:
    """The codes `route` answers (its own, not ANY's), in the table's order."""
    if route not in ROUTES and route != ANY:
        raise KeyError(f"unknown route {route!r}: one of {ROUTES} or {ANY!r}")
    return [code for code, error in ERRORS.items() if route in error.routes]


def error_responses(route: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` for a route: one entry per status, its description listing the codes it can carry."""
    from service.schemas import ErrorResponse  # schemas imports nothing from here; keep the import local anyway

    by_status: dict[int, list[str]] = {}
    for code in route_codes(route):
        by_status.setdefault(ERRORS[code].status, []).append(code)
    return {
        status: {
            "model": ErrorResponse,
            "description": "; ".join(f"`{code}`: {ERRORS[code].meaning}" for code in names),
        }
        for status, names in sorted(by_status.items())
    }


def error_table() -> str:
    """docs/api.md's table of the codes, made from ERRORS."""
    rows = [f"| {e.status} | `{code}` | {e.meaning} |" for code, e in ERRORS.items()]
    return "\n".join(["| status | code | when |", "|---|---|---|", *rows])


# Refusals of what a client sent that a flood repeats (service/http/penalty.py slows their answers): the body, its
# fields and image, its rate, and the client's own request limit. Never the refusals a well-behaved client can meet
# (409 ordering, 503 overload, 404 after an expiry).
PENALISED_CODES = frozenset(
    {
        "empty_body",
        "invalid_json",
        "invalid_multipart",
        "ambiguous_content_type",
        "timestamp_gap_too_small",
        "body_timeout",
        "body_too_slow",
        "request_too_large",
        "unsupported_media_type",
        "validation_error",
        "stream_id_mismatch",
        "invalid_image",
        "unsupported_image_size",
        "unsupported_image_format",
        "too_many_client_requests",
    }
)


async def penalise(app: Any, client: str) -> None:
    """Count one penalised refusal of `client` and wait out its penalty, if any (service/http/penalty.py)."""
    penalty = getattr(app.state, "refusal_penalty", None)
    if penalty is not None:
        delay = penalty.record(client)
        if delay:
            await asyncio.sleep(delay)


def client_of(scope: Scope) -> str:
    """The client's address, what its request limit and refusal penalty are counted by: behind a trusted proxy, its
    X-Forwarded-For as uvicorn resolves it into the scope."""
    client = scope.get("client")
    return str(client[0]) if client else "unknown"


async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
    if exc.code in PENALISED_CODES:
        await penalise(request.app, client_of(request.scope))
    return error_response(exc.status, exc.code, exc.message, exc.headers)


_FRAMEWORK_CODES = {404: "not_found", 405: "method_not_allowed"}


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    code = _FRAMEWORK_CODES.get(exc.status_code) or ("http_error" if exc.status_code < 500 else "internal_error")
    return error_response(ERRORS[code].status, code, str(exc.detail), exc.headers)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    await penalise(request.app, client_of(request.scope))
    return error_response(422, "validation_error", format_validation_errors(list(exc.errors())))


async def _client_disconnect(request: Request, exc: ClientDisconnect) -> Response:
    """The client left: one INFO line, a 499 for the metrics (nobody receives it), never a 500."""
    log.info("client disconnected before its answer: %s %s", request.method, request.url.path)
    return Response(status_code=CLIENT_CLOSED_REQUEST)


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return error_response(500, "internal_error", f"internal error: {type(exc).__name__}")


def install_error_handlers(app: FastAPI) -> None:
    # Starlette types every handler as taking Exception, not the class it is registered for: hence the ignores.
    app.add_exception_handler(ApiError, _api_error)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(ClientDisconnect, _client_disconnect)  # type: ignore[arg-type]
    app.add_exception_handler(Exception, _unexpected_error)
