"""tools.decode_speed times every posted form it is given, through the service's decode path."""

from __future__ import annotations

from pathlib import Path

import pytest

from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence
from tools.decode_speed import main


def test_each_form_is_timed(tmp_path: Path, capsys):
    folder = write_sequence(run_simulation(5, 2, "test", 1152, Difficulty(), name="dec"), tmp_path, polar=True)
    args = ["--cartesian", str(folder / "Navtech_Cartesian"), "--polar", str(folder / "Navtech_Polar")]
    assert main([*args, "--repeats", "2"]) == 0
    rows = {line.split("  ")[0]: line for line in capsys.readouterr().out.splitlines()[1:]}
    assert set(rows) == {"full Cartesian scan", "polar scan", "256 px crop"}
    assert all(float(line.split()[-5]) > 0 for line in rows.values())


def test_an_empty_folder_is_refused(tmp_path: Path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--cartesian", str(tmp_path)])
    assert exit_info.value.code == 2 and "no PNG files" in capsys.readouterr().err
