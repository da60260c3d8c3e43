"""rafd serve: one uvicorn process serving the model over HTTP.

Every service setting (service/settings.py) is a flag (service/serve_flags.py generates them from the Settings model)
and an RAFD_* environment variable; a flag wins over the variable. Scale out with more processes/containers,
routing each stream id to one replica (a stream's buffer lives in its process).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from rafd.cli.flags import prog
from rafd.model_files import checkpoint_given_for_onnx
from service.serve_flags import add_settings_flags, settings_overrides


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog("serve"),
        description="Serve RaFD radar detection over HTTP. Without --model (RAFD_MODEL_PATH) it serves the model "
        "shipped in the package.",
    )
    parser.add_argument("--host", default="127.0.0.1", help="interface to bind (0.0.0.0 in a container)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port to listen on (default %(default)s)")
    parser.add_argument(
        "--log-level",
        default="info",
        choices=["critical", "error", "warning", "info", "debug"],
        help="log level of the service and uvicorn (default %(default)s)",
    )
    add_settings_flags(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from service.settings import Settings

    overrides: dict[str, Any] = settings_overrides(args)  # Settings field -> the flag's text
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        print(f"rafd-serve: invalid settings: {exc}", file=sys.stderr)
        return 2
    if settings.model_path is None:
        try:
            from rafd.assets import default_onnx  # shipped with the package; imported only when needed

            settings.model_path = Path(default_onnx())
        except (ImportError, OSError, ValueError) as exc:
            print(
                f"rafd-serve: no --model given and no default model shipped with the package ({exc})", file=sys.stderr
            )
            return 2
    if not Path(settings.model_path).is_file():
        print(f"rafd-serve: model file {settings.model_path} does not exist", file=sys.stderr)
        return 2
    wrong_kind = checkpoint_given_for_onnx(settings.model_path)
    if wrong_kind:
        print(f"rafd-serve: {wrong_kind}", file=sys.stderr)
        return 2

    from service.app import create_app
    from service.http.server import serve

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        app = create_app(settings)
    except ValueError as exc:  # e.g. a malformed API key or an unreadable RAFD_API_KEYS_FILE
        print(f"rafd-serve: {exc}", file=sys.stderr)
        return 2
    serve(app, settings, host=args.host, port=args.port, log_level=args.log_level)
    return 0


if __name__ == "__main__":
    sys.exit(main())
