"""rafd odometry: ego_poses.csv written for a sequence or a whole root in parallel, resumable, evaluated against true
poses; bad folders fail clearly."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from rafd.cli.odometry import main as odometry_main
from rafd.data import read_ego_poses, read_sequence
from rafd.geometry import relative_pose
from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence


@pytest.fixture(scope="module")
def sim_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    truth = run_simulation(43, 5, "test", 256, Difficulty(), name="odo_cli")
    return write_sequence(truth, tmp_path_factory.mktemp("odo_cli") / "odo_cli")


def test_cli_writes_ego_poses_and_refuses_to_overwrite(sim_folder: Path, tmp_path: Path, capsys) -> None:
    folder = Path(shutil.copytree(sim_folder, tmp_path / "seq"))
    (folder / "ego_poses.csv").unlink()
    assert odometry_main([str(folder)]) == 0
    table = read_ego_poses(folder / "ego_poses.csv")
    assert list(table) == [1, 2, 3, 4, 5]
    sequence = read_sequence(folder)
    assert sequence.pose_source == "file"
    np.testing.assert_allclose([f.timestamp for f in sequence.frames], [table[n][0] for n in table], atol=1e-6)
    truth = read_ego_poses(sim_folder / "ego_poses.csv")
    true_step = relative_pose(truth[5][1], truth[1][1])
    np.testing.assert_allclose(sequence.poses[-1][:2], true_step[:2], atol=0.3)  # 4 chained pairs

    before = (folder / "ego_poses.csv").read_bytes()
    capsys.readouterr()
    assert odometry_main([str(folder)]) == 0  # resumable: a prepared sequence is skipped, untouched
    assert "0 sequences given poses" in capsys.readouterr().out and (folder / "ego_poses.csv").read_bytes() == before
    assert odometry_main([str(folder), "--force"]) == 0
    assert odometry_main([str(folder), "--out", str(tmp_path / "other.csv")]) == 0
    assert (tmp_path / "other.csv").read_bytes() == before


def test_cli_prepares_a_whole_root_in_parallel_and_resumes(sim_folder: Path, tmp_path: Path, capsys) -> None:
    """Every sequence of the chosen splits without poses gets them; others and other splits are left alone."""
    root = tmp_path / "root"
    done = Path(shutil.copytree(sim_folder, root / "a" / "done"))
    todo = [Path(shutil.copytree(sim_folder, root / "b" / f"todo{k}")) for k in range(2)]
    other_split = Path(shutil.copytree(sim_folder, root / "c" / "other"))
    for folder in todo + [other_split]:
        (folder / "ego_poses.csv").unlink()
    meta = json.loads((other_split / "meta.json").read_text())
    (other_split / "meta.json").write_text(json.dumps({**meta, "set": "train_good_weather"}))
    (done / "ego_poses.csv").write_text((done / "ego_poses.csv").read_text())  # untouched below
    stamp = (done / "ego_poses.csv").stat().st_mtime_ns
    assert odometry_main([str(root), "--split", "test", "--workers", "2"]) == 0
    assert "2 sequences given poses (10 frames" in capsys.readouterr().out
    assert all((folder / "ego_poses.csv").is_file() for folder in todo)
    assert not (other_split / "ego_poses.csv").exists()
    assert (done / "ego_poses.csv").stat().st_mtime_ns == stamp
    first, second = (read_ego_poses(folder / "ego_poses.csv") for folder in todo)
    np.testing.assert_array_equal(np.stack([first[n][1] for n in first]), np.stack([second[n][1] for n in second]))


def test_cli_bad_folders_fail_clearly(tmp_path: Path, capsys) -> None:
    assert odometry_main([str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err
    assert odometry_main([str(tmp_path)]) == 2
    assert "no sequence folders" in capsys.readouterr().err
    assert odometry_main([str(tmp_path), "--workers", "0"]) == 2


def test_cli_evaluate_reports_errors(sim_folder: Path, capsys) -> None:
    before = (sim_folder / "ego_poses.csv").read_bytes()
    assert odometry_main([str(sim_folder), "--evaluate"]) == 0
    out = capsys.readouterr().out
    assert "4 pairs" in out and "translation error m mean" in out and "ms/pair" in out
    assert (sim_folder / "ego_poses.csv").read_bytes() == before
