"""Oxford / Boreas style sequence folders (rafd.data.native_folder): listing, numbering, ground-truth odometry as
poses, Boreas folders without a timestamps index, errors; and the real Oxford sample end to end."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.data import read_sequence
from rafd.data.dataset import find_sequences
from rafd.data.native_folder import microseconds_text, read_ground_truth_odometry
from rafd.geometry import relative_pose
from rafd.scans.native import NativeSource
from tests.rafd.scans.test_native import native_png

HEADER = (
    "source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw,source_radar_timestamp,destination_radar_timestamp"
)


def write_folder(root: Path, stamps: list[int], index: bool = True, bins: int = 3768, bin_m: float = 0.0432) -> Path:
    (root / "radar").mkdir(parents=True)
    for k, stamp in enumerate(stamps):
        cv2.imwrite(str(root / "radar" / f"{stamp}.png"), native_png(bins, [(90.0, 10.0 + k)], bin_m, start_us=stamp))
    if index:
        (root / "radar.timestamps").write_text("".join(f"{stamp} 1\n" for stamp in stamps))
    return root


def write_odometry(path: Path, rows: list[tuple[int, int, float, float, float]]) -> None:
    """Rows (newer, older, x forward, y right, yaw clockwise) in Oxford's radar_odometry.csv layout."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [HEADER] + [f"0,0,{x},{y},0,0,0,{yaw},{newer},{older}" for newer, older, x, y, yaw in rows]
    path.write_text("\n".join(lines) + "\n")


STAMPS = [1_547_131_046_000_000 + 250_000 * k for k in range(4)]


def test_a_native_folder_reads_like_a_radiate_sequence(tmp_path: Path):
    folder = write_folder(tmp_path / "seq", STAMPS)
    sequence = read_sequence(folder, estimate_poses=False)
    assert [f.number for f in sequence.frames] == [1, 2, 3, 4] and sequence.image_size == 1152
    assert [f.timestamp_text for f in sequence.frames] == [microseconds_text(s) for s in STAMPS]
    assert sequence.frames[1].timestamp_ns == STAMPS[1] * 1000
    assert isinstance(sequence.frames[0].polar, NativeSource) and sequence.frames[0].polar.fmt.name == "oxford"
    assert sequence.load_image(0).shape == (1152, 1152) and sequence.poses is None and not sequence.annotated
    assert find_sequences(tmp_path) == [folder]


def test_ground_truth_odometry_becomes_the_poses_in_this_projects_axes(tmp_path: Path):
    """Rows chain through scans not on disk; (x fwd, y right, yaw clockwise) -> (x right, y fwd, yaw CCW)."""
    folder = write_folder(tmp_path / "seq", [STAMPS[0], STAMPS[1], STAMPS[3]])
    hidden = STAMPS[2]  # a scan of the recording that is not in this folder
    write_odometry(
        folder / "gt" / "radar_odometry.csv",
        [
            (STAMPS[1], STAMPS[0], 2.0, 0.1, 0.01),
            (hidden, STAMPS[1], 2.0, 0.0, 0.0),
            (STAMPS[3], hidden, 2.0, 0.0, 0.0),
        ],
    )
    sequence = read_sequence(folder)
    assert sequence.pose_source == "file"
    np.testing.assert_allclose(relative_pose(sequence.poses[1], sequence.poses[0]), [0.1, 2.0, -0.01], atol=1e-12)
    np.testing.assert_allclose(relative_pose(sequence.poses[2], sequence.poses[1]), [0.0, 4.0, 0.0], atol=1e-12)


def test_broken_chains_and_indexes_fail_clearly(tmp_path: Path):
    folder = write_folder(tmp_path / "seq", STAMPS[:2])
    write_odometry(folder / "gt" / "radar_odometry.csv", [])
    with pytest.raises(ValueError, match="do not lead from scan"):
        read_sequence(folder)
    with pytest.raises(ValueError, match="not Oxford's radar_odometry.csv"):
        (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
        read_ground_truth_odometry(tmp_path / "bad.csv", STAMPS[:2])
    other = write_folder(tmp_path / "other", STAMPS[:2])
    (other / "radar.timestamps").write_text(f"{STAMPS[0]} 1\n")
    with pytest.raises(ValueError, match="disagrees with the scans"):
        read_sequence(other, estimate_poses=False)
    (other / "radar.timestamps").write_text(f"{STAMPS[0]} 1\n{STAMPS[1]} 1\n{STAMPS[2]} 1\n")
    with pytest.raises(FileNotFoundError, match="not in"):
        read_sequence(other, estimate_poses=False)


def test_a_boreas_folder_without_an_index_is_listed_by_its_file_names(tmp_path: Path):
    folder = write_folder(tmp_path / "boreas", STAMPS[:3], index=False, bins=3360, bin_m=0.0596)
    (folder / "meta.json").write_text('{"name": "boreas-test", "set": "test", "native_format": "boreas"}')
    sequence = read_sequence(folder, estimate_poses=False)
    assert sequence.name == "boreas-test" and sequence.split == "test" and len(sequence) == 3
    assert sequence.frames[0].polar.fmt.name == "boreas"  # type: ignore[union-attr]
    # the return written at 10 m right of the radar lands there on the converted scan
    scan = sequence.load_image(0).astype(np.float32)
    v, u = np.unravel_index(np.argmax(cv2.GaussianBlur(scan, (0, 0), 2.0)), scan.shape)
    assert abs((u + 0.5 - 576) * 0.173611 - 10.0) < 0.6 and abs(576 - v - 0.5) * 0.173611 < 0.6


def test_the_real_oxford_sample_reads_with_its_ground_truth(oxford_sample: Path):
    sequence = read_sequence(oxford_sample)
    assert len(sequence) == 13 and sequence.pose_source == "file"
    steps = [relative_pose(sequence.poses[k], sequence.poses[k - 1]) for k in range(1, 13)]
    forward = [step[1] for k, step in enumerate(steps, 1) if k != 11]  # frames 11-12 are 2 s apart
    assert all(0.8 < f < 2.6 for f in forward) and 9.0 < steps[10][1] < 11.0
    scan = sequence.load_image(0)
    assert scan.shape == (1152, 1152) and scan.dtype == np.uint8 and scan[576 - 300 : 576 + 300].mean() > 5
