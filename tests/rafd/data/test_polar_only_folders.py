"""Polar-only sequence folders (Navtech_Polar/ + Navtech_Polar.txt): read, converted on load, found, refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.data import read_sequence
from rafd.data.dataset import find_sequences
from rafd.data.folders import list_frames
from rafd.data.radiate_files import parse_radiate_time
from rafd.scans.polar import PolarConventions, polar_to_cartesian, scan_agreement
from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory):
    """(truth, folder with both Cartesian and polar scans): 4 frames of 256 px."""
    truth = run_simulation(31, 4, "test", 256, Difficulty(), name="sim_31_0")
    return truth, write_sequence(truth, tmp_path_factory.mktemp("polar") / "sim_31_0", polar=True)


@pytest.fixture
def polar_only(simulated, tmp_path: Path) -> Path:
    """A copy of the simulated folder without its Cartesian scans."""
    folder = Path(shutil.copytree(simulated[1], tmp_path / "sim_31_0"))
    shutil.rmtree(folder / "Navtech_Cartesian")
    (folder / "Navtech_Cartesian.txt").unlink()
    return folder


def test_the_simulator_writes_radiates_polar_layout(simulated):
    truth, folder = simulated
    scans = sorted((folder / "Navtech_Polar").glob("*.png"))
    assert [p.name for p in scans] == [f"{n:06d}.png" for n in range(1, 5)]
    polar = cv2.imread(str(scans[0]), cv2.IMREAD_UNCHANGED)
    assert polar.shape == (576, 400) and polar.dtype == np.uint8
    assert (folder / "Navtech_Polar.txt").read_text() == (folder / "Navtech_Cartesian.txt").read_text()
    np.testing.assert_array_equal(polar, truth.polar_scans[0])


def test_both_scans_present_reads_the_cartesian_ones(simulated):
    sequence = read_sequence(simulated[1])
    assert all(frame.polar is None for frame in sequence.frames)
    assert sequence.frames[0].image_path.parent.name == "Navtech_Cartesian"


def test_polar_only_simulated_folder_reads_like_its_cartesian_twin(simulated, polar_only: Path):
    truth, both = simulated
    cartesian, polar = read_sequence(both), read_sequence(polar_only)
    assert polar.image_size == 256 and polar.name == "sim_31_0" and polar.pose_source == "file"
    assert [f.number for f in polar.frames] == [1, 2, 3, 4]
    assert [f.timestamp for f in polar.frames] == [f.timestamp for f in cartesian.frames]
    np.testing.assert_allclose(polar.poses, cartesian.poses)
    same_centre = PolarConventions(centre_offset=(0.0, 0.0))  # the simulator puts the radar at the image centre
    for index, (p, c) in enumerate(zip(polar.frames, cartesian.frames)):
        assert p.image_path.parent.name == "Navtech_Polar" and p.polar is not None
        scan = p.load()
        assert scan.shape == (256, 256) and scan.dtype == np.uint8
        np.testing.assert_array_equal(scan, list_frames(polar_only).load(index))
        np.testing.assert_array_equal(scan, polar_to_cartesian(truth.polar_scans[index], 256))  # RADIATE's grid
        # The same scene as the simulator's own Cartesian scan: the written polar keeps RADIATE's 17 cm range bins
        # (every other 9 cm bin of the simulator), so fine speckle differs (measured: MAD 4.0, correlation 0.93
        # with the radar at the simulator's centre; RADIATE's half-pixel offset alone takes it to about 0.8).
        mad, correlation = scan_agreement(
            polar_to_cartesian(truth.polar_scans[index], 256, conventions=same_centre), truth.images[index]
        )
        assert mad < 6.0 and correlation > 0.9
        assert [o.id for o in p.objects] == [o.id for o in c.objects]
        for a, b in zip(p.objects, c.objects):
            np.testing.assert_allclose(a.box, b.box)


def test_real_polar_scans_read_as_radiates_cartesian_frames(radiate_polar_sample: Path, radiate_sample: Path):
    sequence = read_sequence(radiate_polar_sample)  # no meta.json, no annotations: warned, not fatal
    assert sequence.image_size == 1152 and [f.number for f in sequence.frames] == [1, 2]
    lines = (radiate_sample / "Navtech_Cartesian.txt").read_text().splitlines()[:2]
    assert [f.timestamp for f in sequence.frames] == [parse_radiate_time(line.split()[3])[0] for line in lines]
    for frame in sequence.frames:
        reference = cv2.imread(str(radiate_sample / "Navtech_Cartesian" / frame.image_path.name), cv2.IMREAD_GRAYSCALE)
        mad, correlation = scan_agreement(frame.load(), reference)
        assert mad < 3.5 and correlation > 0.97
    # Odometry on the converted scans agrees with odometry on RADIATE's own Cartesian scans.
    assert sequence.pose_source == "odometry"
    from rafd.odometry.registration import estimate_relative_pose

    reference_step = estimate_relative_pose(
        *(cv2.imread(str(radiate_sample / "Navtech_Cartesian" / f"{n:06d}.png"), cv2.IMREAD_GRAYSCALE) for n in (1, 2)),
        0.173611,
    )
    assert np.hypot(*(sequence.poses[1, :2] - reference_step[:2])) < 0.2
    assert abs(sequence.poses[1, 2] - reference_step[2]) < np.deg2rad(0.5)


def test_find_sequences_finds_polar_only_folders(simulated, polar_only: Path, tmp_path: Path):
    assert find_sequences(polar_only) == [polar_only]
    root = tmp_path / "root"
    shutil.copytree(polar_only, root / "a_polar")
    shutil.copytree(simulated[1], root / "b_both")
    (root / "c_empty" / "deeper").mkdir(parents=True)
    assert [p.name for p in find_sequences(root)] == ["a_polar", "b_both"]


def test_polar_only_folders_refuse_bad_data_naming_the_file(polar_only: Path):
    bad = polar_only / "Navtech_Polar" / "000002.png"
    cv2.imwrite(str(bad), np.zeros((576, 399), np.uint8))
    with pytest.raises(ValueError, match="scans differ in size"):
        read_sequence(polar_only)
    bad.write_bytes(b"not a png at all, but long enough to fill a header")
    with pytest.raises(ValueError, match="000002.png"):
        read_sequence(polar_only)
    (polar_only / "Navtech_Polar.txt").unlink()
    with pytest.raises(FileNotFoundError, match="Navtech_Polar.txt"):
        read_sequence(polar_only)


def test_polar_only_meta_image_size_must_be_even(polar_only: Path):
    meta = json.loads((polar_only / "meta.json").read_text())
    meta["image_size"] = 255
    (polar_only / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="image_size must be an even"):
        read_sequence(polar_only)
