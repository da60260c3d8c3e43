"""The multipart form of POST /detect, derived from the one definition of its fields (service.schemas.DetectBody):
the form's field names, how each is read, and its OpenAPI schema.

The form is the JSON body flattened: a nested object's fields become NAME_FIELD, written together or not at all
(pose -> pose_x, pose_y, pose_yaw); the image is the file field `image`. A field added to DetectBody is a form field
and in both OpenAPI forms with nothing else to write.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any, Literal

from pydantic import BaseModel

from service.schemas import DetectBody

FORM_FILES = ("image",)
IMAGE_DESCRIPTION = "the PNG file, 8-bit greyscale (a Cartesian, polar or native radar scan)"


@dataclass(frozen=True)
class FormField:
    """One field of the form: where its value goes in the body and how its text is read."""

    name: str  # as posted (pose_x)
    path: tuple[str, ...]  # where in the body (("pose", "x"))
    kind: Literal["number", "text"]
    schema: dict[str, Any]  # its JSON schema (constraints and description), for OpenAPI


def _without_null(prop: dict[str, Any]) -> dict[str, Any]:
    """An optional field's schema without its `null` alternative (the form omits an absent field)."""
    options = [p for p in prop.get("anyOf", ()) if p.get("type") != "null"]
    if len(options) != 1:
        return prop
    merged = {**options[0], **{k: v for k, v in prop.items() if k not in ("anyOf", "default", "title")}}
    return merged


def _kind(name: str, prop: dict[str, Any]) -> Literal["number", "text"]:
    kinds = {"number": "number", "string": "text"}
    if prop.get("type") not in kinds:
        raise TypeError(f"{name}: a form field must be a number or a string, not {prop.get('type')!r}")
    return "number" if prop["type"] == "number" else "text"


@cache
def form_fields(model: type[BaseModel] = DetectBody) -> tuple[FormField, ...]:
    """The model's fields as form fields, in its order."""
    schema = model.model_json_schema(ref_template="{model}")
    fields = []
    for name, prop in schema["properties"].items():
        prop = _without_null(prop)
        if "$ref" in prop:  # a nested object: one form field per field of it
            nested = schema["$defs"][prop["$ref"]]
            for sub, sub_prop in nested["properties"].items():
                described = {k: v for k, v in sub_prop.items() if k != "title"}
                described["description"] = f"{name}.{sub}: {sub_prop.get('description', '')} ({prop['description']})"
                fields.append(FormField(f"{name}_{sub}", (name, sub), _kind(name, sub_prop), described))
        else:
            fields.append(FormField(name, (name,), _kind(name, prop), {k: v for k, v in prop.items() if k != "title"}))
    return tuple(fields)


def form_field_names(model: type[BaseModel] = DetectBody) -> tuple[str, ...]:
    return tuple(field.name for field in form_fields(model))


def form_groups(model: type[BaseModel] = DetectBody) -> dict[str, tuple[str, ...]]:
    """Nested objects -> their form fields, which come together or not at all."""
    groups: dict[str, list[str]] = {}
    for field in form_fields(model):
        if len(field.path) > 1:
            groups.setdefault(field.path[0], []).append(field.name)
    return {name: tuple(names) for name, names in groups.items()}


def multipart_schema(model: type[BaseModel] = DetectBody) -> dict[str, Any]:
    """The OpenAPI schema of the multipart form: every field of the JSON body (flattened) and the image file."""
    required = set(model.model_json_schema().get("required", ()))
    properties: dict[str, Any] = {field.name: field.schema for field in form_fields(model)}
    properties["image"] = {"type": "string", "format": "binary", "description": IMAGE_DESCRIPTION}
    return {
        "type": "object",
        "required": [f.name for f in form_fields(model) if f.path[0] in required and len(f.path) == 1] + ["image"],
        "properties": properties,
        "additionalProperties": False,
    }
