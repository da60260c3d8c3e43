"""rafd.protocol's stream-id rule is the service's: it refuses what the server refuses, the service's schema is built
from it, and a name becomes a valid stream id with a suffix."""

from __future__ import annotations

import pytest
from pydantic import TypeAdapter, ValidationError

from rafd import protocol
from rafd.protocol import STREAM_ID_MAX_LENGTH, is_stream_id, stream_id_from
from service import schemas

SERVER_STREAM_ID = TypeAdapter(schemas.StreamId)

# (stream id, whether the service takes it): the edges of each part of the rule.
STREAM_IDS = [
    ("a", True),
    ("car-7", True),
    ("A.b_c~d:e@f+g-h0", True),
    ("x" * STREAM_ID_MAX_LENGTH, True),
    ("x" * (STREAM_ID_MAX_LENGTH + 1), False),
    ("", False),
    (".", False),
    ("..", False),
    ("...", True),
    (".a", True),
    ("..a", True),
    ("a.", True),
    ("-", True),
    ("." + "x" * (STREAM_ID_MAX_LENGTH - 1), True),
    ("." + "x" * STREAM_ID_MAX_LENGTH, False),
    (".." + "x" * (STREAM_ID_MAX_LENGTH - 2), True),
    (".." + "x" * (STREAM_ID_MAX_LENGTH - 1), False),
    ("../detect", False),
    ("a b", False),
    ("a\tb", False),
    ("a\n", False),
    ("a%2F", False),
    ("a?b", False),
    ("a#b", False),
    ("ä", False),
    ("\u0661", False),  # an Arabic-Indic digit: "0-9" is ASCII on both sides
]


def server_takes(stream_id: str) -> bool:
    try:
        SERVER_STREAM_ID.validate_python(stream_id)
    except ValidationError:
        return False
    return True


@pytest.mark.parametrize(("stream_id", "valid"), STREAM_IDS)
def test_the_stream_id_rule_refuses_what_the_server_refuses(stream_id: str, valid: bool):
    assert is_stream_id(stream_id) is valid
    assert server_takes(stream_id) is valid


def test_the_service_schema_is_built_from_the_rule_defined_here():
    assert schemas.STREAM_ID_PATTERN is protocol.STREAM_ID_PATTERN
    published = SERVER_STREAM_ID.json_schema()
    assert published["maxLength"] == STREAM_ID_MAX_LENGTH and published["pattern"] == protocol.STREAM_ID_PATTERN
    assert published["description"] == protocol.STREAM_ID_RULE
    # the pattern the API has published since the rule was written (OpenAPI clients compiled it)
    assert protocol.STREAM_ID_PATTERN == (
        r"^(?:[A-Za-z0-9_~:@+\-][A-Za-z0-9._~:@+\-]{0,127}"
        r"|\.[A-Za-z0-9_~:@+\-][A-Za-z0-9._~:@+\-]{0,126}"
        r"|\.\.[A-Za-z0-9._~:@+\-]{1,126})$"
    )


@pytest.mark.parametrize("name", ["city 7/0", "ä-ö", "", ".", "..", "x" * 200])
def test_a_name_becomes_a_stream_id_with_a_suffix(name: str):
    safe = stream_id_from(name)
    assert len(safe) == len(name) and all(is_stream_id("a" + c) for c in safe)
    assert is_stream_id(safe[: STREAM_ID_MAX_LENGTH - 7] + "-3fa9c2")  # as `rafd client` names a run's stream
