"""Parse POST /detect bodies strictly: JSON (base64 image) or multipart/form-data (image file + form fields).

JSON: no duplicate keys, no NaN / Infinity / out-of-range numbers, no unknown keys, no type coercion (a
timestamp is a JSON number: "1.5" and true are refused). Bounded cost: a JSON body's structural characters are
counted as it streams in (`StructureCount`: a detect request has a few keys, one object in another and no long
array), and a body with more is refused as soon as its count passes the bound, unparsed and unread past that piece
(a body of 200k keys or numbers: after its first 64 KiB); the rest is parsed on the parse executor, off the event
loop, by orjson (strict: UTF-8, no NaN / Infinity, no trailing data). Multipart: the JSON body's fields flattened
(service.body.form: stream_id, timestamp, pose_x, pose_y, pose_yaw (all three or none), previous_timestamp,
range_resolution_m) and the
file field `image`, each at most once; numbers are written as JSON numbers. Unknown fields are refused (a typo like
`pose_yw` must not silently drop the pose).
The stream id may come from the body, the X-Stream-Id header or the path; all that are given must agree.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np
import orjson
from fastapi import Request
from pydantic import BaseModel, ValidationError

from service.body.form import FORM_FILES, form_field_names, form_fields, form_groups
from service.body.images import PostedImage
from service.body.multipart import Part, read_form
from service.http.errors import MAX_LISTED_ERRORS, MAX_LOCATION_CHARS, ApiError, format_validation_errors
from service.schemas import DetectBody, DetectFields, DetectJson, Pose

JSON = "application/json"
MULTIPART = "multipart/form-data"
JSON_FIELDS = frozenset(DetectJson.model_fields)
POSE_FIELDS = frozenset(Pose.model_fields)
# RFC 8259's number grammar: what a multipart number field may hold (no "nan", "inf", " 1", "1_000", "0x1").
NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][+-]?[0-9]+)?")
# The most of each structural character a JSON body may hold, counted before it is parsed. A complete request (keys
# stream_id, timestamp, pose {x, y, yaw}, image) has 18 quotes, 6 commas (one in a data URL prefix), 2 objects and
# no array; base64 and stream ids hold none of them. The bounds leave room for whitespace-free mistakes to get
# pydantic's message (a wrong type, an unknown key) while a body of many keys or numbers is refused unparsed.
MAX_JSON_QUOTES = 64
MAX_JSON_COMMAS = 32
MAX_JSON_OBJECTS = 4
MAX_JSON_ARRAYS = 4

JsonParser = Callable[[bytes, "StructureCount"], Awaitable[tuple[DetectBody, str]]]


async def _parse_here(raw: bytes, counted: StructureCount) -> tuple[DetectBody, str]:
    return parse_json_body(raw, counted)


async def parse_detect_request(
    request: Request,
    stream_hint: str | None,
    upload_check: Callable[[], Callable[[bytes], None]] | None = None,
    parse_json: JsonParser = _parse_here,
) -> tuple[DetectFields, PostedImage]:
    """-> (validated fields with the resolved stream id, the image as posted); 400/415/422 with the reason.

    `upload_check()` gives a feeder that sees a multipart image upload piece by piece as it streams in;
    `parse_json` runs `parse_json_body` (the service: on its parse executor)."""
    if len(request.headers.getlist("content-type")) > 1:  # which one would a proxy or another parser have read?
        raise ApiError("ambiguous_content_type", "the request has more than one Content-Type header; send exactly one")
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    image: PostedImage  # text from a JSON body, bytes from a form
    if media_type == JSON:
        raw, counted = await read_json(request)
        body, image = await parse_json(raw, counted)
    elif media_type == MULTIPART:
        body, image = await _parse_form(request, {"image": upload_check()} if upload_check else {})
    else:
        raise ApiError(
            "unsupported_media_type", f"Content-Type must be {JSON} or {MULTIPART}, got {media_type[:64] or 'none'!r}"
        )
    return resolve_stream_id(body, stream_hint), image


def resolve_stream_id(body: DetectBody, stream_hint: str | None) -> DetectFields:
    stream_id = body.stream_id or stream_hint  # a posted stream_id is never empty (StreamId: min_length=1)
    if stream_id is None:
        raise ApiError(
            "validation_error",
            "stream_id: Field required (in the body, the X-Stream-Id header or the path /streams/{stream_id}/detect)",
        )
    if body.stream_id is not None and stream_hint is not None and body.stream_id != stream_hint:
        raise ApiError(
            "stream_id_mismatch",
            f"the body's stream_id {body.stream_id!r} differs from "
            f"{stream_hint!r} given in the X-Stream-Id header or the path",
        )
    previous = body.previous_timestamp
    if previous is not None and previous >= body.timestamp:
        raise ApiError(
            "validation_error",
            f"previous_timestamp ({previous!r}) must be before timestamp ({body.timestamp!r}): it names the frame "
            "this stream sent before this one",
        )
    return DetectFields.model_construct(**{**dict(body), "stream_id": stream_id})  # the body's values, validated


# ---------------------------------------------------------------------------------------------------- JSON
class _DuplicateKey(ValueError):
    pass


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise _DuplicateKey(key)
        obj[key] = value
    return obj


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:32]} is out of range")
    return value


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not allowed")


def load_json(raw: bytes) -> Any:
    """JSON text -> Python with the standard library, naming a duplicated key; refuses non-finite numbers. The slow
    path: used once `check_structure` bounded the body, when it holds backslashes or a duplicate was found."""
    try:
        return json.loads(raw, object_pairs_hook=_object, parse_float=_finite_float, parse_constant=_no_constant)
    except _DuplicateKey as exc:
        raise ApiError(
            "validation_error", f"key {str(exc)[:MAX_LOCATION_CHARS]!r} appears more than once in a JSON object"
        ) from exc
    except (ValueError, RecursionError) as exc:
        raise ApiError(
            "invalid_json",
            f"the body is not valid JSON (NaN, Infinity and out-of-range numbers are not allowed): {exc}",
        ) from exc


def _refuse_unknown_keys(obj: dict[str, Any], allowed: frozenset[str], where: str) -> None:
    """Before pydantic: a body with 100k extra keys is refused by listing a few, not by building 100k errors."""
    unknown = [key for key in obj if key not in allowed]
    if unknown:
        listed = ", ".join(repr(key[:MAX_LOCATION_CHARS]) for key in unknown[:MAX_LISTED_ERRORS])
        more = f" and {len(unknown) - MAX_LISTED_ERRORS} more" if len(unknown) > MAX_LISTED_ERRORS else ""
        raise ApiError("validation_error", f"unknown {where}keys {listed}{more}; allowed: {sorted(allowed)}")


def _validate(model: type[BaseModel], data: Any) -> Any:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ApiError("validation_error", format_validation_errors(exc.errors())) from exc


class StructureCount:
    """The structural characters of a JSON body, counted piece by piece as it arrives; 422 once past the bounds.

    A piece is searched for each character (memchr: ~3 us per 64 KiB of base64, which holds none) and counted only
    where it holds one, so a scan's image costs little and a hostile body is refused at its first piece."""

    CHARACTERS = (("quotes", ord('"')), ("commas", ord(",")), ("objects", ord("{")), ("arrays", ord("[")))

    def __init__(self) -> None:
        self.quotes = self.commas = self.objects = self.arrays = self.backslashes = 0

    def feed(self, piece: bytes) -> None:
        view: np.ndarray | None = None
        for name, char in (*self.CHARACTERS, ("backslashes", ord("\\"))):
            if piece.find(char) != -1:
                view = np.frombuffer(piece, np.uint8) if view is None else view
                setattr(self, name, getattr(self, name) + int(np.count_nonzero(view == char)))
        if (
            self.quotes > MAX_JSON_QUOTES
            or self.commas > MAX_JSON_COMMAS
            or self.objects > MAX_JSON_OBJECTS
            or self.arrays > MAX_JSON_ARRAYS
        ):
            raise ApiError(
                "validation_error",
                f"the body has {self.quotes} quotes, {self.commas} commas, {self.objects} objects and {self.arrays} "
                f"arrays so far: more than a detect request can have (at most {MAX_JSON_QUOTES}, {MAX_JSON_COMMAS}, "
                f"{MAX_JSON_OBJECTS} and {MAX_JSON_ARRAYS}: the keys stream_id, timestamp, pose {{x, y, yaw}} and "
                "image); refused unparsed",
                headers={"Connection": "close"},  # the rest of the body is not read
            )


def check_structure(raw: bytes) -> StructureCount:
    """A whole body's structure count (422 beyond the bounds)."""
    counted = StructureCount()
    counted.feed(raw)
    return counted


async def read_json(request: Request) -> tuple[bytes, StructureCount]:
    """The body as it streams in, its structure counted piece by piece (refused at the first piece past the bounds)."""
    counted, pieces = StructureCount(), []
    async for piece in request.stream():
        if piece:
            counted.feed(piece)
            pieces.append(piece)
    return b"".join(pieces), counted


def _quotes(value: Any) -> int:
    """The quote characters `value` takes when written as JSON without escapes."""
    if isinstance(value, str):
        return 2
    if isinstance(value, dict):
        return sum(2 + _quotes(item) for item in value.values())
    if isinstance(value, list):
        return sum(_quotes(item) for item in value)
    return 0


def parse_json(raw: bytes, counted: StructureCount | None = None) -> Any:
    """Strict JSON -> Python: orjson, then the duplicate-key check. Without escapes, every quote of the body belongs
    to a key or a string, so a body whose quotes outnumber its parsed keys and strings repeated a key (orjson keeps
    the last one); with escapes, the standard library's parser names the key (bounded by the structure count)."""
    counted = counted or check_structure(raw)
    quotes, backslashes = counted.quotes, counted.backslashes
    try:
        data = orjson.loads(raw)
    except orjson.JSONDecodeError as exc:
        raise ApiError(
            "invalid_json",
            f"the body is not valid JSON (UTF-8; NaN, Infinity and out-of-range numbers are not allowed): {exc}",
        ) from exc
    if backslashes or quotes != _quotes(data):
        data = load_json(raw)  # raises naming the duplicated key, if any
    return data


def parse_json_body(raw: bytes, counted: StructureCount | None = None) -> tuple[DetectBody, str]:
    """A JSON detect body -> (validated fields, the image text); `counted`: its structure count, when taken as it
    arrived."""
    if not raw or raw.isspace():
        raise ApiError("empty_body", "the request body is empty; expected a JSON object")
    data = parse_json(raw, counted)
    if not isinstance(data, dict):
        raise ApiError("validation_error", f"expected a JSON object, got {type(data).__name__}")
    _refuse_unknown_keys(data, JSON_FIELDS, "")
    if isinstance(data.get("pose"), dict):
        _refuse_unknown_keys(data["pose"], POSE_FIELDS, "pose ")
    parsed = _validate(DetectJson, data)
    return parsed, parsed.image


# ---------------------------------------------------------------------------------------------------- multipart
def _text(part: Part) -> str:
    try:
        return part.data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ApiError("validation_error", f"form field {part.name!r} is not UTF-8 text") from exc


def _number(name: str, text: str) -> float:
    if NUMBER.fullmatch(text):
        value = float(text)
        if math.isfinite(value):
            return value
    raise ApiError(
        "validation_error",
        f"form field {name!r} must be a finite number written like 1574859771.74 or -0.5, got {text[:32]!r}",
    )


async def _parse_form(request: Request, inspect: dict[str, Callable[[bytes], None]]) -> tuple[DetectBody, bytes]:
    content_type = request.headers.get("content-type", "")
    parts = await read_form(request.stream(), content_type, FORM_FILES, form_field_names(), inspect)
    if "image" not in parts:
        raise ApiError("validation_error", "form field 'image' (the PNG file) is missing")
    for group, names in form_groups().items():
        given = [name for name in names if name in parts]
        if given and len(given) != len(names):
            raise ApiError(
                "validation_error", f"{group} form fields must come together: got {given}, need {list(names)}"
            )
    values: dict[str, Any] = {}
    for field in form_fields():
        if field.name in parts:
            text = _text(parts[field.name])
            place = values
            for key in field.path[:-1]:
                place = place.setdefault(key, {})
            place[field.path[-1]] = _number(field.name, text) if field.kind == "number" else text
    return _validate(DetectBody, values), parts["image"].data
