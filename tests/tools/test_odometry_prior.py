"""tools.odometry_prior prints both ways' per-frame medians on a simulated sequence and refuses a too-short one."""

from __future__ import annotations

from pathlib import Path

import pytest

from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence
from tools.odometry_prior import main


def test_it_times_both_ways(tmp_path: Path, capsys):
    folder = write_sequence(run_simulation(3, 4, "test", 256, Difficulty(), name="cost"), tmp_path)
    assert main([str(folder), "--rounds", "1"]) == 0
    out = capsys.readouterr().out
    assert "3 frames x 1 rounds, 256 px views" in out
    medians = [float(line.split("median ")[1].split(" ms")[0]) for line in out.splitlines() if "median" in line]
    assert len(medians) == 2 and all(m > 0 for m in medians)


def test_a_too_short_sequence_is_refused(tmp_path: Path, capsys):
    folder = write_sequence(run_simulation(3, 2, "test", 256, Difficulty(), name="short"), tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main([str(folder)])
    assert exit_info.value.code == 2 and "needs 3 or more" in capsys.readouterr().err
