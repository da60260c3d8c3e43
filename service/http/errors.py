"""One error shape for every 4xx/5xx: {"error": {"code": str, "message": str}}, from one registry of codes.

Every code the service can answer is in `ERRORS` (status and meaning); `ApiError` only takes a registered code,
the OpenAPI responses are built from the registry (`error_responses`) and docs/api.md documents each code
(a test checks all three agree). Messages are capped (`MAX_MESSAGE_CHARS`) so an error never grows with the input.
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
    meaning: str


ERRORS: Mapping[str, ErrorCode] = {
    "empty_body": ErrorCode(400, "the request body is empty"),
    "invalid_json": ErrorCode(400, "the body is not valid JSON (NaN, Infinity and out-of-range numbers included)"),
    "invalid_multipart": ErrorCode(400, "the multipart/form-data body cannot be parsed (boundary, part headers)"),
    "ambiguous_content_type": ErrorCode(400, "the request has more than one Content-Type header"),
    "missing_api_key": ErrorCode(401, "API keys are configured and the request carries none"),
    "invalid_api_key": ErrorCode(401, "API keys are configured and the request's key is not one of them"),
    "not_found": ErrorCode(404, "no such route"),
    "stream_not_found": ErrorCode(
        404, "no such stream of this API key (never seen, deleted or expired; no frame of it accepted or in flight)"
    ),
    "method_not_allowed": ErrorCode(405, "the route does not take this HTTP method"),
    "body_timeout": ErrorCode(
        408, "the body did not arrive within RAFD_BODY_TIMEOUT_S (its frame held its stream's place meanwhile)"
    ),
    "body_too_slow": ErrorCode(
        408,
        "after its first RAFD_BODY_RATE_GRACE_S seconds the body arrived slower than RAFD_MIN_BODY_BYTES_PER_S "
        "bytes per second on average",
    ),
    "request_header_timeout": ErrorCode(
        408, "the request line and headers did not arrive within RAFD_HEADER_TIMEOUT_S (the connection is closed)"
    ),
    "timestamp_not_increasing": ErrorCode(
        409,
        "the frame's timestamp is not after the stream's last accepted frame, or after a frame of that "
        "stream that arrived earlier and is still queued",
    ),
    "pose_source_conflict": ErrorCode(409, "a request pose on a stream whose world frame was anchored by odometry"),
    "stream_reset": ErrorCode(
        409,
        "the stream was deleted (reset) while this frame waited or ran; the frame belongs to the ended "
        "chain and was not used: send it again to start the new chain",
    ),
    "request_too_large": ErrorCode(413, "the body exceeds RAFD_MAX_REQUEST_BYTES"),
    "request_line_too_long": ErrorCode(
        414, "the request line exceeds RAFD_MAX_REQUEST_LINE_BYTES (the connection is closed)"
    ),
    "unsupported_media_type": ErrorCode(415, "Content-Type is neither application/json nor multipart/form-data"),
    "validation_error": ErrorCode(
        422,
        "a field is missing, unknown, duplicated or of the wrong type (no coercion: a JSON timestamp must be "
        "a number, not a string or a boolean), or a path, query or header value is invalid",
    ),
    "stream_id_mismatch": ErrorCode(
        422, "the stream id in the X-Stream-Id header, the URL path and the body do not all agree"
    ),
    "invalid_image": ErrorCode(
        422,
        "the image is not valid base64 / not a PNG / corrupt, or its chunk structure is refused before "
        "decoding (too many or too large ancillary chunks, image data that inflates beyond its header's size)",
    ),
    "timestamp_gap_too_small": ErrorCode(
        422, "the frame follows the stream's last accepted frame by less than RAFD_MIN_FRAME_GAP_S seconds"
    ),
    "implausible_motion": ErrorCode(
        422,
        "the frame's pose (the request's or odometry's) moved faster than RAFD_MAX_SPEED_MPS since the stream's last "
        "accepted frame; the frame is refused and the stream keeps its last pose",
    ),
    "unsupported_image_size": ErrorCode(422, "the PNG is not one of the accepted square sizes"),
    "unsupported_image_format": ErrorCode(422, "the PNG is not 8-bit greyscale (colour type 0, bit depth 8)"),
    "stream_queue_full": ErrorCode(429, "RAFD_STREAM_QUEUE_LIMIT frames of this stream are already queued"),
    "too_many_client_requests": ErrorCode(
        429, "RAFD_MAX_REQUESTS_PER_CLIENT requests of this client (by address) are already unfinished"
    ),
    "request_header_too_large": ErrorCode(
        431,
        "more than RAFD_MAX_HEADERS header fields or more than RAFD_MAX_HEADER_BYTES bytes of them (the connection "
        "is closed)",
    ),
    "internal_error": ErrorCode(500, "the model or the service failed; no stream changed"),
    "odometry_failed": ErrorCode(500, "odometry returned no finite ego motion; no stream changed"),
    "not_ready": ErrorCode(503, "the model is loading or warming up, or failed to load"),
    "overloaded": ErrorCode(
        503,
        "too many requests receiving their body or in flight, or the parse / decode / odometry / model queue is "
        "full; retry after the Retry-After header's seconds",
    ),
    "odometry_unavailable": ErrorCode(503, "this build cannot estimate ego motion: send a pose with every frame"),
    "http_error": ErrorCode(400, "any other refusal by the HTTP framework (not expected)"),
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


# A name for codes answered by one check, usable in a route's `responses`: the API key middleware answers either.
CODE_GROUPS: Mapping[str, tuple[str, ...]] = {"unauthorized": ("missing_api_key", "invalid_api_key")}


def expand_codes(codes: Sequence[str]) -> list[str]:
    """Codes with every group name (CODE_GROUPS) replaced by its codes."""
    return [member for code in codes for member in CODE_GROUPS.get(code, (code,))]


def error_responses(*codes: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` for a route: one entry per status, its description listing the codes it can carry."""
    from service.schemas import ErrorResponse  # schemas imports nothing from here; keep the import local anyway

    by_status: dict[int, list[str]] = {}
    for code in expand_codes(codes):
        by_status.setdefault(ERRORS[code].status, []).append(code)
    return {
        status: {
            "model": ErrorResponse,
            "description": "; ".join(f"`{code}`: {ERRORS[code].meaning}" for code in names),
        }
        for status, names in sorted(by_status.items())
    }


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
