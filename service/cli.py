"""`rafd-serve [--model model.onnx] [--host 127.0.0.1] [--port 8000]`: one uvicorn process serving the model.

Other settings come from RAFD_* environment variables (see service/settings.py). Scale out with more
processes/containers, routing each stream id to one replica (a stream's buffer lives in its process).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-serve", description="Serve RaFD radar detection over HTTP.")
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        help="ONNX model from rafd-export (default: RAFD_MODEL_PATH, else the model shipped in the package)",
    )
    parser.add_argument("--host", default="127.0.0.1", help="interface to bind (0.0.0.0 in a container)")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="onnxruntime intra-op threads (default: the CPUs this process may use)",
    )
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from service.settings import Settings

    overrides: dict[str, Any] = {}  # Settings field -> value (of that field's type)
    if args.model is not None:
        overrides["model_path"] = args.model
    if args.threads is not None:
        overrides["threads"] = args.threads
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

    from service.app import create_app
    from service.server import serve

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
