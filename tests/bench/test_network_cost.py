"""bench.network_cost: the shipped config and a variant timed side by side; a bad setting is refused by name."""

from __future__ import annotations

import pytest

from bench.network_cost import main

pytest.importorskip("torch")


def test_a_narrower_network_is_timed_beside_the_shipped_one(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--variant", "neck.channels=16 enhance.num_blocks=1", "--tiles", "2", "--rounds", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "2 tiles per scan" in lines[0]
    shipped, narrow = lines[1].split(), lines[2].split()
    assert shipped[0] == "shipped" and shipped[-1] == "1.00x"
    assert narrow[0] == "neck.channels=16" and int(narrow[-7]) < int(shipped[-7])  # fewer parameters


def test_an_unknown_setting_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--variant", "neck.chanels=16"]) == 2
    assert "neck.chanels" in capsys.readouterr().err
