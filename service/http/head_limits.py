"""uvicorn's httptools protocol with limits on the request head, enforced before anything reaches the app.

uvicorn on httptools has none: one 64 MiB header answered 200 after ~5 s, and 8 connections of 128 MiB headers
held readiness for up to 30 s and grew the process by 1 GB, all before the API key was checked. This subclass
keeps uvicorn's parser and request cycle (the fastest path measured here) and adds:

- the request line (method, target, version) at most `max_request_line_bytes`: 414 beyond;
- at most `max_headers` header fields and `max_header_bytes` of them (names, values and separators): 431 beyond,
  checked on every field as it is parsed AND on the raw bytes of a head still incomplete (httptools buffers a field
  until its end, so one endless field is caught from the bytes received);
- the head complete within `header_timeout_s` of the connection (for its first request) or of the request's first
  byte (on a kept-alive connection): 408 beyond. uvicorn itself times out only idle kept-alive connections;
- a connection whose response ended before its request body had fully arrived (a refusal that did not read the
  body) is closed, so an unread body cannot be trickled in forever; and every response that STARTS before its
  request's body has fully arrived says so with `Connection: close` (whichever layer answered: 401, 408, 413, 429,
  503, ...), so a pooled client (nginx's upstream keep-alive, httpx) never sends its next request on a connection the
  server is about to close ("Server disconnected without sending a response");
- closing after a refusal lingers: the answer is sent, the sending side shut (the client reads the answer and an
  end of file), and what the client still sends is read and dropped for at most `LINGER_S` seconds or
  `LINGER_BYTES` bytes before the socket is closed. A socket closed with unread input is reset, which can drop
  the answer before the client reads it;
- each request's `scope["extensions"]["rafd.arrival"]["at"]`: time.monotonic() of its first byte (arrival order).

Each refusal is a JSON error of the service's shape, closes the connection, is counted through `on_refused` and by
the refusal penalty (service/http/penalty.py, shared with the app): a peer refused too often has each further refusal
answered only after the penalty, its connection not read meanwhile, so a flood of endless heads cannot take the
cores. The subclass relies on uvicorn's HttpToolsProtocol internals (its parser callbacks and `cycle`): uvicorn is
pinned in pyproject.toml, and tests/service/test_client_isolation.py exercises every limit on a real server.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import httptools
from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol

from service.http.errors import ERRORS, error_body
from service.http.intake import ARRIVAL
from service.http.penalty import RefusalPenalty

log = logging.getLogger(__name__)

LINGER_S = 1.0
LINGER_BYTES = 64 * 1024


@dataclass(frozen=True)
class HeadLimits:
    max_request_line_bytes: int = 8 * 1024
    max_headers: int = 100
    max_header_bytes: int = 32 * 1024
    header_timeout_s: float = 10.0


class HeadRefused(Exception):
    """Raised from a parser callback: the head breaks a limit (httptools re-raises it as the context of its own
    HttpParserCallbackError)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class LimitedHttpToolsProtocol(HttpToolsProtocol):
    limits: ClassVar[HeadLimits] = HeadLimits()
    penalty: ClassVar[RefusalPenalty | None] = None

    @staticmethod
    def on_refused(status: int) -> None:
        """Called with the status of each refusal (`limited_protocol` sets it: the app's metrics count them)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._in_head = True  # the next bytes belong to a request head
        self._crossed = False  # a head or a message ended within the chunk being fed
        self._head_bytes = 0  # raw bytes of the head so far (whole chunks received while in the head)
        self._line_bytes = 0
        self._headers_seen = 0
        self._header_bytes = 0
        self._head_timer: asyncio.TimerHandle | None = None
        self._lingering = -1  # bytes dropped since the connection started closing (-1: not closing)
        self._close_announced: object | None = None  # the cycle whose answer said `Connection: close` (this layer)

    # ------------------------------------------------------------------ connection
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_head_timer()  # a connection that never sends a head is closed too

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        """uvicorn's data_received, plus the head limits (its own turns every parser error into a 400)."""
        if self._lingering >= 0:  # closing: what the client still sends is dropped
            self._lingering += len(data)
            if self._lingering > LINGER_BYTES:
                self.transport.close()
            return
        self._unset_keepalive_if_required()
        # The raw bytes of an incomplete head are counted only for a chunk that lies wholly inside one head (it began
        # in a head and no head or message ended within it); a chunk that ends a message and starts the next head
        # is not counted (the fields it completes still are, in on_header), so the raw count lags by one read.
        counting = self._in_head
        self._crossed = False
        try:
            self.parser.feed_data(data)
        except httptools.HttpParserCallbackError as exc:
            if isinstance(exc.__context__, HeadRefused):
                self._refuse(exc.__context__)
            else:
                self._bad_request()
            return
        except httptools.HttpParserUpgrade:
            if self._should_upgrade():
                self.handle_websocket_upgrade()
            else:
                self._unsupported_upgrade_warning()
            return
        except httptools.HttpParserError:
            self._bad_request()
            return
        if counting and self._in_head and not self._crossed:
            self._head_bytes += len(data)
            limits = self.limits
            if self._head_bytes > limits.max_request_line_bytes + limits.max_header_bytes:
                if self._headers_seen == 0 and self._line_bytes > limits.max_request_line_bytes:
                    self._refuse(_line_too_long(limits))
                else:
                    self._refuse(_head_too_large(limits))

    # ------------------------------------------------------------------ parser callbacks
    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_head = True
        self._head_bytes = self._line_bytes = self._headers_seen = self._header_bytes = 0
        self.scope["extensions"] = {ARRIVAL: {"at": time.monotonic()}}
        if self._head_timer is None:  # a kept-alive connection's next request: its head is timed from now
            self._arm_head_timer()

    def on_url(self, url: bytes) -> None:
        self._line_bytes += len(url)
        if self._line_bytes > self.limits.max_request_line_bytes:
            raise _line_too_long(self.limits)
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._headers_seen += 1
        self._header_bytes += len(name) + len(value) + 4  # "name: value\r\n"
        limits = self.limits
        if self._headers_seen > limits.max_headers or self._header_bytes > limits.max_header_bytes:
            raise _head_too_large(limits)
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        self._in_head = False
        self._crossed = True
        self._cancel_head_timer()
        previous = self.cycle
        super().on_headers_complete()
        if self.cycle is not None and self.cycle is not previous:
            self._announce_early_close(self.cycle)

    def _announce_early_close(self, cycle: Any) -> None:
        """Wrap the cycle's `send` (its ASGI task has not started yet): an answer that starts while the request's body
        is still arriving gets `Connection: close`, since this connection closes after it (`on_response_complete`).
        uvicorn, seeing the header, would close the socket outright at the answer's end, which resets a connection
        with unread input and can drop the answer; the lingering close here is kept instead."""
        send = cycle.send

        async def send_announcing_close(message: Any) -> None:
            if message["type"] != "http.response.start" or cycle.response_started or not cycle.more_body:
                await send(message)
                return
            headers = list(message.get("headers", []))
            if not any(name.lower() == b"connection" and b"close" in value.lower() for name, value in headers):
                headers.append((b"connection", b"close"))
            keep_alive = cycle.keep_alive
            await send({**message, "headers": headers})
            cycle.keep_alive = keep_alive  # uvicorn cleared it for the header: the lingering close ends this one
            self._close_announced = cycle

        cycle.send = send_announcing_close

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._in_head = True
        self._crossed = True

    def on_response_complete(self) -> None:
        cycle = self.cycle
        super().on_response_complete()
        announced = cycle is not None and cycle is self._close_announced
        if cycle is not None and (cycle.more_body or announced) and not self.transport.is_closing():
            self._linger()  # answered before its body arrived: the rest of it is not waited for

    # ------------------------------------------------------------------ refusals
    def _arm_head_timer(self) -> None:
        self._cancel_head_timer()
        self._head_timer = self.loop.call_later(self.limits.header_timeout_s, self._head_timed_out)

    def _cancel_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self.transport.is_closing():
            return
        if self.cycle is not None and not self.cycle.response_complete:
            self.cycle.keep_alive = False  # a pipelined head is late: close once the answer in progress is sent
            return
        self._refuse(
            HeadRefused(
                "request_header_timeout",
                f"the request line and headers did not arrive within {self.limits.header_timeout_s:g} s "
                "(RAFD_HEADER_TIMEOUT_S)",
            )
        )

    def _refuse(self, refusal: HeadRefused) -> None:
        """Answer the refusal (the service's JSON error shape) and close the connection; after the penalty, if any,
        with the connection not read meanwhile."""
        self._cancel_head_timer()
        self._unset_keepalive_if_required()
        self._lingering = 0  # from now on, what the client sends is dropped
        status = ERRORS[refusal.code].status
        log.debug("refused a request head from %s: %s", self.client, refusal.message)
        self.on_refused(status)
        if self.cycle is not None and not self.cycle.response_complete:
            self.transport.close()  # an answer is in progress on this connection: nothing can be added to it
            return
        delay = self.penalty.record(self.client[0]) if self.penalty is not None and self.client else 0.0
        if delay:
            self.transport.pause_reading()
            self.loop.call_later(delay, self._answer_refusal, refusal, status)
        else:
            self._answer_refusal(refusal, status)

    def _answer_refusal(self, refusal: HeadRefused, status: int) -> None:
        if self.transport.is_closing():
            return
        body = json.dumps(error_body(refusal.code, refusal.message)).encode()
        head = [STATUS_LINE[status]]
        for name, value in self.server_state.default_headers:
            head += [name, b": ", value, b"\r\n"]
        head += [
            b"content-type: application/json\r\n",
            b"content-length: " + str(len(body)).encode() + b"\r\n",
            b"connection: close\r\n\r\n",
            body,
        ]
        self.transport.write(b"".join(head))
        self.transport.resume_reading()
        self._linger()

    def _linger(self) -> None:
        """Close after the answer: shut the sending side now, drop input, close the socket at LINGER_S at most."""
        self._cancel_head_timer()
        self._unset_keepalive_if_required()
        self._lingering = 0
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(LINGER_S, self.transport.close)

    def _bad_request(self) -> None:
        msg = "Invalid HTTP request received."
        self.logger.warning(msg)
        self.send_400_response(msg)


def _line_too_long(limits: HeadLimits) -> HeadRefused:
    return HeadRefused(
        "request_line_too_long",
        f"the request line exceeds {limits.max_request_line_bytes} bytes (RAFD_MAX_REQUEST_LINE_BYTES)",
    )


def _head_too_large(limits: HeadLimits) -> HeadRefused:
    return HeadRefused(
        "request_header_too_large",
        f"the request has more than {limits.max_headers} header fields (RAFD_MAX_HEADERS) or more than "
        f"{limits.max_header_bytes} bytes of them (RAFD_MAX_HEADER_BYTES)",
    )


def limited_protocol(
    limits: HeadLimits, on_refused: Callable[[int], None] | None = None, penalty: RefusalPenalty | None = None
) -> type[asyncio.Protocol]:
    """The protocol class for uvicorn's `http=` option, with these limits (and the app's refusal penalty)."""
    attributes: dict[str, Any] = {"limits": limits, "penalty": penalty}
    if on_refused is not None:
        attributes["on_refused"] = staticmethod(on_refused)
    protocol: type[asyncio.Protocol] = type("RaFDHttpProtocol", (LimitedHttpToolsProtocol,), attributes)
    return protocol
