"""A bag as a sequence: read_sequence, rafd odometry (poses beside the bag, then used) and rafd polar read it through
the same reader as rafd client."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rafd.cli.odometry import main as odometry_main
from rafd.cli.polar import main as polar_main
from rafd.data import read_sequence
from rafd.data.dataset import find_sequences, select_sequences
from rafd.ros.sequence import is_bag, poses_file
from rafd.scans.native import parse_native_scan, to_cartesian


def test_a_bag_reads_as_a_sequence(navtech_bag: Path, scans):
    assert is_bag(navtech_bag) and is_bag(next(navtech_bag.glob("*.mcap"))) and not is_bag(navtech_bag.parent)
    sequence = read_sequence(navtech_bag, estimate_poses=False)
    assert len(sequence) == 3 and sequence.poses is None and not sequence.annotated and sequence.split is None
    stamps_us = [int(np.ascontiguousarray(s[199, :8]).view("<i8")[0]) for s in scans]
    assert [f.timestamp_ns for f in sequence.frames] == [us * 1000 for us in stamps_us]
    from rafd.scans.native import NATIVE_FORMATS

    expected = to_cartesian(parse_native_scan(scans[1], NATIVE_FORMATS["oxford"].with_range_bin(0.0864)))
    np.testing.assert_array_equal(sequence.frames[1].load(), expected)  # the bag's bin size, not the width's guess
    assert find_sequences(navtech_bag) == [navtech_bag]
    assert select_sequences(navtech_bag, "test") == ([navtech_bag], {None: 1})


def test_odometry_writes_poses_beside_the_bag_and_they_are_used(navtech_bag: Path, tmp_path: Path):
    assert odometry_main([str(navtech_bag), "--quiet"]) == 0
    assert poses_file(navtech_bag).is_file() and not (navtech_bag / "ego_poses.csv").exists()
    sequence = read_sequence(navtech_bag, estimate_poses=False)
    assert sequence.pose_source == "file" and sequence.poses is not None and sequence.poses.shape == (3, 3)
    assert polar_main([str(navtech_bag), "--out", str(tmp_path / "converted"), "--quiet"]) == 0
    assert len(list((tmp_path / "converted" / "Navtech_Cartesian").glob("*.png"))) == 3
