"""Write docs/api.md's table of error codes from the one table in service/http/errors.py (`ERRORS`).

python -m tools.api_tables [--write]      # print the table, or put it between docs/api.md's markers
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.http.errors import error_table

API_DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"
BEGIN, END = "<!-- error-table:begin (python -m tools.api_tables --write) -->", "<!-- error-table:end -->"


def with_table(text: str) -> str:
    """The page with the table between its markers replaced by the current one."""
    start, stop = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[:start] + "\n" + error_table() + "\n" + text[stop:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.api_tables", description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help=f"write the table into {API_DOC}")
    args = parser.parse_args(argv)
    if not args.write:
        print(error_table())
        return 0
    API_DOC.write_text(with_table(API_DOC.read_text()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
