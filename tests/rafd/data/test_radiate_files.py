"""RADIATE's per-sequence files parsed on their own (rafd.data.radiate_files): timestamps as the RADIATE SDK reads
them, the recording condition from meta.json. Read through whole folders: tests/rafd/data/test_reader.py."""

from __future__ import annotations

import pytest

from rafd.data.radiate_files import meta_condition, parse_radiate_time


@pytest.mark.parametrize(
    "text, seconds, canonical",
    [
        ("1574859771.744660272", 1574859771.744660272, "1574859771.744660272"),  # exact: 9 digits
        ("1574859771.74466027", 1574859771.074466027, "1574859771.074466027"),  # short: nanoseconds, not a decimal
        ("1574859771.074466027", 1574859771.074466027, "1574859771.074466027"),  # the same time, padded on disk
        ("1574859772.5", 1574859772.000000005, "1574859772.000000005"),
        ("1574859772", 1574859772.0, "1574859772.000000000"),  # no fraction
    ],
    ids=["exact", "short", "padded", "one-digit", "integer"],
)
def test_timestamps_are_read_as_the_radiate_sdk_reads_them(text, seconds, canonical) -> None:
    parsed, written = parse_radiate_time(text)
    assert written == canonical
    assert parsed == pytest.approx(seconds, abs=1e-6)


@pytest.mark.parametrize(
    ("meta", "condition"),
    [
        ({"type": "simulated", "weather": "rain"}, "rain"),  # the simulator: its weather, not its type
        ({"type": "night"}, "night"),  # RADIATE: the recording condition is the type
        ({"type": "simulated", "weather": None}, None),  # a simulated drive without weather names none
        ({}, None),
    ],
)
def test_the_recording_condition_comes_from_meta_json(meta: dict, condition: str | None) -> None:
    assert meta_condition(meta) == condition
