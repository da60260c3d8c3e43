"""bench.tracking: the tracker's cost per scan prints for every velocity candidate, and the answer's growth."""

from __future__ import annotations

import pytest

from bench.tracking import main


def test_prints_every_case_and_the_answer_growth(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--boxes", "8", "--frames", "3", "--rounds", "1", "--quiet"]) == 0
    out = capsys.readouterr().out
    for case in ("filter        none", "filter_flow   one crop", "flow_box      whole scan (25 tiles)"):
        assert case in out
    assert "bytes of JSON per box" in out
