"""multipart/form-data read straight from the request stream with python-multipart, in memory, on the event loop.

Why not Starlette's `request.form()`: it spools files over 1 MB to temporary files through the shared thread pool
(the pool health checks waited on), keeps the LAST of duplicated fields silently, and answers malformed bodies
with an undocumented 400. Here the body (already capped by RAFD_MAX_REQUEST_BYTES) is parsed as it streams in;
every part must be a known field, appear once, and be a file or a plain field as the API says, plain fields
are short, and a file part can be inspected piece by piece as it arrives (a hostile upload is refused before the
rest of it is received).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Collection, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from service.http.errors import ApiError

if TYPE_CHECKING:  # defined for type checkers only
    from python_multipart.multipart import MultipartCallbacks

# Plain fields carry a stream id (<= 128 characters) or a number.
MAX_FIELD_BYTES = 1024
MAX_PART_HEADER_BYTES = 1024


@dataclass
class Part:
    name: str
    filename: str | None
    chunks: list[bytes] = field(default_factory=list)
    size: int = 0

    @property
    def data(self) -> bytes:
        return b"".join(self.chunks)


def boundary_of(content_type: str) -> bytes:
    # Two boundary parameters: python-multipart keeps the last, another parser (a proxy's, a WAF's) may keep the first
    # and read other parts than this service does. Refuse the ambiguity. (A boundary cannot hold ';', RFC 2046.)
    names = [param.split("=", 1)[0].strip().lower() for param in content_type.split(";")[1:]]
    if names.count("boundary") > 1:
        raise ApiError("invalid_multipart", "the multipart/form-data Content-Type has more than one boundary parameter")
    _, options = parse_options_header(content_type)
    boundary = options.get(b"boundary", b"")
    if not boundary or len(boundary) > 70:  # RFC 2046: 1-70 characters
        raise ApiError("invalid_multipart", "the multipart/form-data Content-Type has no valid boundary parameter")
    return boundary


class _FormReader:
    """python-multipart callbacks -> the parts by name, refusing unknown, duplicated or oversized parts."""

    def __init__(
        self, files: Collection[str], fields: Collection[str], inspect: Mapping[str, Callable[[bytes], None]]
    ) -> None:
        self.files, self.fields = set(files), set(fields)
        self.inspect = inspect
        self.parts: dict[str, Part] = {}
        self.current: Part | None = None
        self.header_name = bytearray()
        self.header_value = bytearray()
        self.headers: dict[bytes, bytes] = {}
        self.ended = False

    def callbacks(self) -> MultipartCallbacks:
        return {
            "on_part_begin": self.part_begin,
            "on_header_field": self.header_field,
            "on_header_value": self.header_value_data,
            "on_header_end": self.header_end,
            "on_headers_finished": self.headers_finished,
            "on_part_data": self.part_data,
            "on_part_end": self.part_end,
            "on_end": self.end,
        }

    def part_begin(self) -> None:
        self.headers = {}
        self.current = None

    def header_field(self, data: bytes, start: int, end: int) -> None:
        self.header_name += data[start:end]
        self._check_header_size()

    def header_value_data(self, data: bytes, start: int, end: int) -> None:
        self.header_value += data[start:end]
        self._check_header_size()

    def _check_header_size(self) -> None:
        if len(self.header_name) + len(self.header_value) > MAX_PART_HEADER_BYTES:
            raise ApiError("invalid_multipart", f"a multipart part header exceeds {MAX_PART_HEADER_BYTES} bytes")

    def header_end(self) -> None:
        self.headers[bytes(self.header_name).strip().lower()] = bytes(self.header_value).strip()
        self.header_name.clear()
        self.header_value.clear()

    def headers_finished(self) -> None:
        disposition, options = parse_options_header(self.headers.get(b"content-disposition", b"").decode("latin-1"))
        if disposition != b"form-data" or b"name" not in options:
            raise ApiError("invalid_multipart", "a multipart part has no 'Content-Disposition: form-data; name=...'")
        name = options[b"name"].decode("latin-1")
        filename = options[b"filename"].decode("latin-1") if b"filename" in options else None
        allowed = sorted(self.files | self.fields)
        if name not in self.files and name not in self.fields:
            raise ApiError("validation_error", f"unknown form field {name[:64]!r}; allowed: {allowed}")
        if name in self.parts:
            raise ApiError("validation_error", f"form field {name!r} appears more than once; send each field once")
        if name in self.files and filename is None:
            raise ApiError("validation_error", f"form field {name!r} must be a file (the PNG)")
        if name in self.fields and filename is not None:
            raise ApiError("validation_error", f"form field {name!r} must be a plain field, not a file")
        self.current = self.parts[name] = Part(name=name, filename=filename)

    def part_data(self, data: bytes, start: int, end: int) -> None:
        part = self.current
        if part is None:
            raise ApiError("invalid_multipart", "multipart data before a part's headers")
        piece = data[start:end]
        part.chunks.append(piece)
        part.size += len(piece)
        if part.name in self.inspect:
            self.inspect[part.name](piece)
        if part.name in self.fields and part.size > MAX_FIELD_BYTES:
            raise ApiError("validation_error", f"form field {part.name!r} is longer than {MAX_FIELD_BYTES} bytes")

    def part_end(self) -> None:
        self.current = None

    def end(self) -> None:
        self.ended = True


async def read_form(
    stream: AsyncIterator[bytes],
    content_type: str,
    files: Collection[str],
    fields: Collection[str],
    inspect: Mapping[str, Callable[[bytes], None]] | None = None,
) -> dict[str, Part]:
    """Parse the streamed body; -> {name: Part}. 400 invalid_multipart / 422 validation_error on faults.

    `inspect[name]` sees each piece of that part as it arrives and may refuse it (raise) before the rest of the
    body is read."""
    reader = _FormReader(files, fields, inspect or {})
    parser = MultipartParser(boundary_of(content_type), reader.callbacks())
    received = 0
    try:
        async for chunk in stream:
            if chunk:
                received += len(chunk)
                parser.write(chunk)
        parser.finalize()
    except MultipartParseError as exc:
        raise ApiError("invalid_multipart", f"the multipart/form-data body is malformed: {exc}") from exc
    if received == 0:
        raise ApiError("empty_body", "the request body is empty; expected multipart/form-data parts")
    if not reader.ended:
        raise ApiError("invalid_multipart", "the multipart/form-data body ends before its closing boundary")
    return reader.parts
