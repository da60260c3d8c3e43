"""ego_poses.csv: exact round trip, documented header, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rafd.data.poses import POSES_HEADER, read_ego_poses, write_ego_poses


def test_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    poses = rng.normal(size=(7, 3)) * [100.0, 100.0, 3.0]
    stamps = 1574859771.744660272 + np.arange(7) * 0.25
    path = write_ego_poses(tmp_path / "ego_poses.csv", [1, 2, 3, 5, 6, 7, 9], stamps, poses)
    assert path.read_text().splitlines()[0] == ",".join(POSES_HEADER) == "frame,timestamp,x,y,yaw"
    table = read_ego_poses(path)
    assert list(table) == [1, 2, 3, 5, 6, 7, 9]
    np.testing.assert_array_equal(np.stack([table[k][1] for k in table]), poses)
    np.testing.assert_allclose([table[k][0] for k in table], stamps, atol=1e-6)


def test_writer_rejects_inconsistent_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="differ in length"):
        write_ego_poses(tmp_path / "p.csv", [1, 2], [0.0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        write_ego_poses(tmp_path / "p.csv", [1], [0.0], np.zeros((1, 2)))
    with pytest.raises(ValueError, match="increasing"):
        write_ego_poses(tmp_path / "p.csv", [2, 1], [0.0, 1.0], np.zeros((2, 3)))
    assert not (tmp_path / "p.csv").exists()


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "header"),
        ("frame,time,x,y,yaw\n1,0,0,0,0\n", "header"),
        ("frame,timestamp,x,y,yaw\n1,0,0,0\n", "columns"),
        ("frame,timestamp,x,y,yaw\n1,0,0,nan,0\n", "non-finite"),
        ("frame,timestamp,x,y,yaw\n1,0,0,0,0\n1,0,0,0,0\n", "twice"),
        ("frame,timestamp,x,y,yaw\n", "no pose rows"),
    ],
)
def test_reader_errors_name_the_file(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "ego_poses.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        read_ego_poses(path)
    assert str(path) in str(info.value)
    with pytest.raises(FileNotFoundError, match="absent.csv"):
        read_ego_poses(tmp_path / "absent.csv")


def test_string_timestamps_are_written_verbatim(tmp_path: Path) -> None:
    path = write_ego_poses(
        tmp_path / "p.csv", [1, 2], ["1574859771.744660272", "1574859771.977525228"], np.zeros((2, 3))
    )
    assert [line.split(",")[1] for line in path.read_text().splitlines()[1:]] == [
        "1574859771.744660272",
        "1574859771.977525228",
    ]
    with pytest.raises(ValueError):
        write_ego_poses(tmp_path / "q.csv", [1], ["soon"], np.zeros((1, 3)))
