"""rafd.scans.polar: RADIATE's polar conventions, the simulator's own polar -> Cartesian path, and RADIATE's images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.geometry import RADIATE_RESOLUTION
from rafd.preprocess import polar_to_cartesian as preprocess_polar_to_cartesian
from rafd.scans.polar import (
    NOMINAL_POLAR,
    RADIATE_POLAR,
    PolarConventions,
    accepts_polar,
    cartesian_size,
    polar_to_cartesian,
    scan_agreement,
    to_radiate_polar,
)
from rafd.sim.sensor import NavtechConfig, NavtechSensor


def _brightest(image: np.ndarray) -> tuple[int, int]:
    """(u, v) pixel index of the maximum."""
    v, u = np.unravel_index(np.argmax(image), image.shape)
    return int(u), int(v)


@pytest.mark.parametrize(
    "column, direction",
    [(0, (0.0, 1.0)), (100, (1.0, 0.0)), (200, (0.0, -1.0)), (300, (-1.0, 0.0)), (50, (0.7071, 0.7071))],
)
def test_azimuth_zero_is_forward_and_azimuth_turns_clockwise(column, direction):
    """A single bright sample at row 288 lands 50 m from the radar in the direction its column names."""
    polar = np.zeros((576, 400), np.uint8)
    polar[287:290, column] = 255  # a target 3 range bins long
    scan = polar_to_cartesian(polar)
    assert scan.shape == (1152, 1152) and scan.dtype == np.uint8
    centre = np.array([576.0, 576.0]) + RADIATE_POLAR.centre_offset  # continuous (u, v) of the radar
    bearing = np.deg2rad((column + RADIATE_POLAR.azimuth_offset) * 0.9)  # clockwise from forward
    metres = (288 + RADIATE_POLAR.range_offset) * RADIATE_RESOLUTION
    expected = centre + metres / RADIATE_RESOLUTION * np.array([np.sin(bearing), -np.cos(bearing)])  # image v down
    u, v = _brightest(scan)
    assert np.hypot(u + 0.5 - expected[0], v + 0.5 - expected[1]) < 1.5, ((u, v), expected)
    x, y = (u + 0.5 - 576.0), (576.0 - v - 0.5)  # ego frame, pixels
    assert np.dot(np.array([x, y]) / np.hypot(x, y), direction) > 0.99


def test_range_rows_grow_outwards_and_the_disc_ends_at_100_m():
    polar = np.full((576, 400), 100, np.uint8)
    scan = polar_to_cartesian(polar)
    assert scan[576, 576] == 100 and scan[576, 1150] == 100  # 99.8 m to the right: still inside
    assert scan[0, 0] == 0 and scan[1151, 1151] == 0  # the corners lie beyond the last bin
    assert cartesian_size(576) == 1152


def test_the_seam_at_forward_interpolates_across_azimuth_399_and_0():
    polar = np.zeros((576, 400), np.uint8)
    polar[:, 399] = 200
    polar[:, 0] = 100
    scan = polar_to_cartesian(polar)
    row = scan[100]  # 82 m ahead: column 399 covers the pixels just left of forward, column 0 just right
    left, right = row[:576][::-1], row[576:]
    assert left[0] > 100 and left[0] < 200 and right[0] >= 100  # blended, not a hard seam
    assert np.abs(np.diff(scan[100, 560:592].astype(int))).max() < 40  # a bin is 7.5 px wide here: no step


def test_the_simulators_own_polar_to_cartesian_path_is_reproduced_exactly():
    """NavtechSensor.to_cartesian ([A, R] polar, its bin-centre conventions) == polar_to_cartesian on the
    transposed polar with the sensor's stated conventions: same geometry, same interpolation."""
    rng = np.random.default_rng(3)
    for range_bin in (RADIATE_RESOLUTION, RADIATE_RESOLUTION / 2.0):  # RADIATE's bins and the simulator's finer ones
        sensor = NavtechSensor(256, config=NavtechConfig(range_bin=range_bin))
        polar = rng.uniform(0.0, 255.0, (sensor.config.azimuths, sensor.num_bins)).astype(np.float32)  # [A, R]
        expected = sensor.to_cartesian(polar)
        ours = polar_to_cartesian(polar.T, size=256, conventions=sensor.polar_conventions)
        difference = np.abs(expected.astype(int) - ours)
        assert difference.max() <= 1 and difference.mean() < 1e-3  # float rounding at a handful of pixels


def test_resampling_onto_radiate_samples_keeps_the_scan():
    """A polar scan resampled onto RADIATE's layout converts to the same Cartesian image as the original under
    its own conventions (up to the radar's half-pixel position on RADIATE's grid and interpolation)."""
    rng = np.random.default_rng(5)
    smooth = cv2.GaussianBlur(rng.uniform(0, 255, (400, 1154)).astype(np.float32), (0, 0), 4.0)  # [A, R]
    own = PolarConventions(
        azimuth_offset=0.5, range_offset=0.5, range_bin=RADIATE_RESOLUTION / 2, centre_offset=(0.0, 0.0)
    )
    radiate = to_radiate_polar(smooth.T, own)
    assert radiate.shape == (576, 400) and radiate.dtype == np.uint8
    same_centre = PolarConventions(centre_offset=(0.0, 0.0))
    mad, correlation = scan_agreement(
        polar_to_cartesian(radiate, 512, conventions=same_centre), polar_to_cartesian(smooth.T, 512, conventions=own)
    )
    assert mad < 1.0 and correlation > 0.99


def test_bad_polar_input_is_refused():
    with pytest.raises(ValueError, match="2-D"):
        polar_to_cartesian(np.zeros((576,), np.uint8))
    with pytest.raises(ValueError, match="8-bit or float"):
        polar_to_cartesian(np.zeros((576, 400), np.int32))
    with pytest.raises(ValueError, match="even"):
        polar_to_cartesian(np.zeros((576, 400), np.uint8), size=101)
    with pytest.raises(ValueError, match="range_bin"):
        PolarConventions(range_bin=0.0)


def test_polar_scans_are_accepted_where_a_full_radiate_scan_is():
    assert accepts_polar(128, RADIATE_RESOLUTION) and not accepts_polar(128, 0.2)


def test_the_preprocessing_path_exposes_the_conversion():
    assert preprocess_polar_to_cartesian is polar_to_cartesian


def test_conversion_comes_close_to_radiates_own_cartesian_images(radiate_polar_sample: Path, radiate_sample: Path):
    """RADIATE made tiny_foggy's Cartesian frames 1-2 from these polar scans: ours agree to about 3 grey levels
    (correlation 0.97) inside the disc, clearly better than the textbook bin-centre reading."""
    for number in (1, 2):
        polar = cv2.imread(str(radiate_polar_sample / "Navtech_Polar" / f"{number:06d}.png"), cv2.IMREAD_GRAYSCALE)
        reference = cv2.imread(str(radiate_sample / "Navtech_Cartesian" / f"{number:06d}.png"), cv2.IMREAD_GRAYSCALE)
        assert polar.shape == (576, 400)
        mad, correlation = scan_agreement(polar_to_cartesian(polar), reference)
        nominal_mad, nominal_correlation = scan_agreement(
            polar_to_cartesian(polar, conventions=NOMINAL_POLAR), reference
        )
        assert mad < 3.5 and correlation > 0.97, (number, mad, correlation)
        assert mad < nominal_mad - 1.0 and correlation > nominal_correlation + 0.02
        # Any other azimuth zero, direction or a mirrored image is far worse.
        mirrored, _ = scan_agreement(polar_to_cartesian(polar[:, ::-1]), reference)
        rotated, _ = scan_agreement(polar_to_cartesian(np.roll(polar, 2, axis=1)), reference)
        assert mirrored > 2 * mad and rotated > 2 * mad
