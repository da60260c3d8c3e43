"""tools.odometry_cost: against a baseline that is the same code, both ways' errors agree exactly (accuracy is
deterministic) and both are timed; the errors are those of the true poses; a missing baseline is refused."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

import rafd.odometry.registration
from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence
from tools.odometry_cost import main


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_sequence(run_simulation(3, 5, "test", 384, Difficulty(), name="ab"), tmp_path_factory.mktemp("ab"))


def test_the_same_code_as_baseline_gives_the_same_errors(drive: Path, tmp_path: Path, capsys):
    baseline = shutil.copy(rafd.odometry.registration.__file__, tmp_path / "odometry_copy.py")
    assert main([str(drive), "--baseline", str(baseline), "--rounds", "2"]) == 0
    out = capsys.readouterr().out
    errors = [line.split(f"{drive}: ")[1] for line in out.splitlines() if "pairs," in line]
    assert len(errors) == 2 and errors[0] == errors[1]  # this tree's and the baseline's
    pairs, translation = re.search(r"(\d+) pairs, translation mean ([\d.]+)", out).groups()
    assert int(pairs) == 4 and float(translation) < 0.174  # within a scan pixel on a simulated straight drive
    costs = [float(m) for m in re.findall(r"CPU per frame median +([\d.]+) ms", out)]
    assert len(costs) == 2 and all(c > 0 for c in costs) and "CPU ratio this tree / baseline" in out


def test_a_missing_baseline_is_refused(drive: Path, tmp_path: Path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(drive), "--baseline", str(tmp_path / "none.py")])
    assert exit_info.value.code == 2 and "no such file" in capsys.readouterr().err
