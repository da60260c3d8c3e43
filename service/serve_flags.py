"""`rafd serve` flags generated from the Settings model: every setting is a flag, so a setting added to
service/settings.py is a flag at once, with no list to keep in step.

A field `max_streams` becomes `--max-streams`; its help is the field's description (every Settings field has one:
a test checks), plus its environment variable and default; its type comes from the annotation (Literal ->
choices, bool -> --name / --no-name, anything else is passed as text and parsed by the Settings model exactly as
the environment variable would be, so a bad value is refused with the same message). Flags not given leave the
setting to its RAFD_* variable, else its default.
"""

from __future__ import annotations

import argparse
import typing
from typing import Any, Literal

from pydantic.fields import FieldInfo

from rafd.cli import flags
from service.settings import Settings

# Extra spellings of a few flags (the documented `rafd serve --model M.onnx`).
ALIASES = {"model_path": ("--model",)}
# What a flag's value is called in the usage line.
METAVARS = {"model_path": "MODEL.onnx", "api_keys": "KEYS", "api_keys_file": "FILE"}


def flag_name(field: str) -> str:
    return "--" + field.replace("_", "-")


NOTES = {"api_keys": "a key on a command line is visible in the process list: prefer --api-keys-file"}


def _default_text(name: str, field: FieldInfo) -> str:
    if field.default_factory is list:
        return "none"
    if field.default_factory is not None:
        return "computed at start-up"
    if field.default is None:
        return "none"
    if isinstance(field.default, (list, tuple)) and not field.default:
        return "none"
    return str(field.default)


def help_text(name: str, field: FieldInfo) -> str:
    what = field.description or name.replace("_", " ")
    note = f" ({NOTES[name]})" if name in NOTES else ""
    env = f"RAFD_{name.upper()}"
    return f"{what}{note} [env {env}; default: {_default_text(name, field)}]".replace("%", "%%")


def add_settings_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per Settings field, in a group of its own; every default is 'not given' (argparse.SUPPRESS)."""
    group = parser.add_argument_group(
        "service settings (each also read from its RAFD_* environment variable; a flag wins over the variable)"
    )
    for name, field in Settings.model_fields.items():
        annotation = flags.without_none(field.annotation)
        options: dict[str, Any] = {
            "dest": f"setting_{name}",
            "default": argparse.SUPPRESS,
            "help": help_text(name, field),
        }
        if annotation is bool:
            options["action"] = argparse.BooleanOptionalAction
        else:
            if typing.get_origin(annotation) is Literal:
                options["choices"] = [str(choice) for choice in typing.get_args(annotation)]
            else:
                options["metavar"] = METAVARS.get(name) or _metavar(name, annotation)
            options["type"] = str  # parsed by the Settings model, as the environment variable is
        group.add_argument(flag_name(name), *ALIASES.get(name, ()), **options)


def _metavar(name: str, annotation: Any) -> str:
    if name.endswith("_s"):
        return "SECONDS"
    if annotation is int:
        return "N"
    if annotation is float:
        return "X"
    return "PATH" if getattr(annotation, "__name__", "") == "Path" else "VALUE"


def settings_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The settings given as flags: field name -> value (text, parsed by Settings)."""
    prefix = "setting_"
    return {key[len(prefix) :]: value for key, value in vars(args).items() if key.startswith(prefix)}
