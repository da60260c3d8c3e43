"""Native polar scans (rafd.scans.native): the layout read from files written here in Oxford's and Boreas' layouts,
where a return lands in the converted scan, wobbling encoders, bad files; and on the real Oxford sample, the
conventions (forward, clockwise, radar at the centre) against the dataset's ground-truth odometry."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.geometry import RADIATE_RESOLUTION, relative_pose
from rafd.scans.native import (
    HEADER_COLUMNS,
    NATIVE_FORMATS,
    OXFORD_RANGE_BINS,
    format_for,
    is_native_shape,
    native_format_name,
    parse_native_scan,
    read_native_scan,
    to_cartesian,
    to_polar,
)

AZIMUTHS = 400
START_US = 1_547_131_046_353_776  # an Oxford scan's time (before Boreas' 2021 upgrade)


def native_png(
    bins: int,
    returns: list[tuple[float, float]],
    range_bin_m: float,
    start_us: int = START_US,
    encoder_first: int = 13,
    wobble: np.ndarray | None = None,
    size_m: float = 0.13,
) -> np.ndarray:
    """uint8 [400, 11 + bins] in the datasets' layout: 4 Hz timestamps, encoder angles 14 counts apart (+ `wobble`
    counts), every row valid, and a bright return 3 azimuths wide and `size_m` deep at each (azimuth degrees clockwise
    from forward, range metres)."""
    image = np.zeros((AZIMUTHS, HEADER_COLUMNS + bins), np.uint8)
    times = start_us + np.round(np.arange(AZIMUTHS) * 625.0).astype(np.int64)  # 0.25 s per turn
    encoder = encoder_first + 14 * np.arange(AZIMUTHS) + (0 if wobble is None else wobble)
    image[:, :8] = times.astype("<i8").view(np.uint8).reshape(AZIMUTHS, 8)
    image[:, 8:10] = encoder.astype("<u2").view(np.uint8).reshape(AZIMUTHS, 2)
    image[:, 10] = 255
    turns = encoder / 5600.0
    for azimuth_deg, range_m in returns:
        row = int(np.argmin(np.abs(((turns * 360.0 - azimuth_deg) + 180.0) % 360.0 - 180.0)))
        column = HEADER_COLUMNS + int(range_m / range_bin_m)
        half = max(1, int(round(size_m / range_bin_m / 2)))
        for r in (row - 1, row, row + 1):
            image[r % AZIMUTHS, column - half : column + half + 1] = 250
    return image


def brightest_metres(scan: np.ndarray) -> np.ndarray:
    """(x right, y forward) metres of the brightest blob's centre in a converted 1152 px scan."""
    blurred = cv2.GaussianBlur(scan.astype(np.float32), (0, 0), 2.0)
    v, u = np.unravel_index(np.argmax(blurred), blurred.shape)
    return np.array([(u + 0.5 - 576) * RADIATE_RESOLUTION, (576 - v - 0.5) * RADIATE_RESOLUTION])


@pytest.mark.parametrize("name, bins", [("oxford", 3768), ("boreas", 3360)])
@pytest.mark.parametrize("azimuth_deg, range_m", [(0.0, 30.0), (90.0, 40.0), (180.0, 20.0), (270.0, 50.0)])
def test_a_return_lands_where_its_azimuth_and_range_say(name: str, bins: int, azimuth_deg: float, range_m: float):
    """Azimuth 0 is forward (image up), a quarter turn clockwise is right (+x); range in the format's bin size."""
    fmt = NATIVE_FORMATS[name]
    scan = parse_native_scan(native_png(bins, [(azimuth_deg, range_m)], fmt.range_bin_m), name)
    assert scan.fmt == fmt and scan.range_bins == bins and scan.timestamp_us == START_US
    expected = range_m * np.array([np.sin(np.radians(azimuth_deg)), np.cos(np.radians(azimuth_deg))])
    np.testing.assert_allclose(brightest_metres(to_cartesian(scan)), expected, atol=0.6)


def test_range_is_averaged_down_without_aliasing():
    """4 Oxford bins make about one RADIATE bin: an alternating bright/dark pattern averages to its mean."""
    bins = 3768
    image = native_png(bins, [], NATIVE_FORMATS["oxford"].range_bin_m)
    image[:, HEADER_COLUMNS::2] = 200  # every other bin
    polar, conventions = to_polar(parse_native_scan(image))
    assert conventions.range_bin == pytest.approx(bins * 0.0432 / polar.shape[0])
    assert abs(conventions.range_bin - RADIATE_RESOLUTION) < 0.001
    assert np.allclose(polar[5:-5], 100.0, atol=1.0)  # a point sampler would give 0 or 200


def test_wobbling_encoder_angles_are_resampled_onto_a_uniform_grid():
    """Early Boreas scans' encoder angles wobble: the converted return still lands at its true azimuth."""
    rng = np.random.default_rng(0)
    wobble = rng.integers(-5, 6, AZIMUTHS)
    wobble[0], wobble[-1] = 0, min(0, wobble[-1])  # the first and last angles stay within the turn
    fmt = NATIVE_FORMATS["boreas"]
    scan = parse_native_scan(native_png(3360, [(90.0, 40.0)], fmt.range_bin_m, wobble=wobble), fmt)
    np.testing.assert_allclose(brightest_metres(to_cartesian(scan)), [40.0, 0.0], atol=0.6)


def test_boreas_picks_its_range_bin_by_the_scans_time():
    assert format_for("boreas", START_US).name == "boreas"
    assert format_for("boreas", 1_700_000_000_000_000).name == "boreas-2021"
    with pytest.raises(ValueError, match="unknown native scan format"):
        format_for("navtech", START_US)


def test_a_scan_without_its_datasets_name_is_read_by_its_width():
    assert native_format_name(HEADER_COLUMNS + OXFORD_RANGE_BINS) == "oxford"
    assert native_format_name(HEADER_COLUMNS + 6848) == "boreas"  # format_for then picks by the scan's time


def test_a_custom_format_overrides_the_table():
    custom = dataclasses.replace(NATIVE_FORMATS["oxford"], name="mine", range_bin_m=0.0864)
    scan = parse_native_scan(native_png(1884, [(90.0, 40.0)], 0.0864), custom)
    np.testing.assert_allclose(brightest_metres(to_cartesian(scan)), [40.0, 0.0], atol=0.6)


def test_bad_native_files_are_refused(tmp_path: Path):
    image = native_png(3768, [], 0.0432)
    backwards = image.copy()
    backwards[:, :8] = image[::-1, :8]
    with pytest.raises(ValueError, match="timestamps decrease"):
        parse_native_scan(backwards)
    beyond = image.copy()
    beyond[5, 8:10] = np.array([0xFF, 0xFF], np.uint8)  # 65535 counts
    with pytest.raises(ValueError, match="encoder angles"):
        parse_native_scan(beyond)
    with pytest.raises(ValueError, match="uint8"):
        parse_native_scan(image.astype(np.uint16))
    (tmp_path / "broken.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="corrupt"):
        read_native_scan(tmp_path / "broken.png")
    with pytest.raises(FileNotFoundError):
        read_native_scan(tmp_path / "missing.png")
    assert is_native_shape(3779, 400) and not is_native_shape(400, 576) and not is_native_shape(1152, 1152)


# ---------------------------------------------------------------- conventions on the real sample
def _motion_signs(sample: Path, transform) -> list[tuple[float, float]]:
    """(estimated forward m, truth forward m), (estimated yaw, truth yaw) per consecutive pair, scans read through
    `transform` (the candidate convention), 512 px around the radar."""
    from rafd.data import read_sequence
    from rafd.odometry.registration import estimate_relative_pose

    sequence = read_sequence(sample, estimate_poses=False)
    scans = [transform(frame.load())[320:832, 320:832] for frame in sequence.frames[:6]]
    out = []
    for k in range(1, len(scans)):
        estimate = estimate_relative_pose(scans[k - 1], scans[k], RADIATE_RESOLUTION)
        truth = relative_pose(sequence.poses[k], sequence.poses[k - 1])
        out.append((estimate, truth))
    return out


def test_oxford_conventions_agree_with_the_ground_truth_odometry(oxford_sample: Path):
    """Forward at encoder angle 0, clockwise: the odometry of the converted scans has the ground truth's signs and
    size on every pair; read mirrored (counter-clockwise) its yaw has the opposite sign, read rotated by a half turn
    its forward motion has."""
    chosen = _motion_signs(oxford_sample, lambda scan: scan)
    for estimate, truth in chosen:
        assert truth[1] > 0.9 and abs(estimate[1] - truth[1]) < 0.2  # forward metres per scan
        assert np.sign(estimate[2]) == np.sign(truth[2]) and abs(estimate[2] - truth[2]) < np.radians(0.3)
    mirrored = _motion_signs(oxford_sample, lambda scan: scan[:, ::-1])  # counter-clockwise reading
    assert all(np.sign(estimate[2]) == -np.sign(truth[2]) for estimate, truth in mirrored)
    turned = _motion_signs(oxford_sample, lambda scan: scan[::-1, ::-1])  # forward at azimuth 180 degrees
    assert all(estimate[1] < 0 < truth[1] for estimate, truth in turned)


# ---------------------------------------------------------------- what a real sensor's header holds (issue 40)
def _with_header(image: np.ndarray, times: np.ndarray | None = None, encoder: np.ndarray | None = None) -> np.ndarray:
    image = image.copy()
    if times is not None:
        image[:, :8] = np.asarray(times, np.int64).astype("<i8").view(np.uint8).reshape(-1, 8)
    if encoder is not None:
        image[:, 8:10] = np.asarray(encoder, np.int64).astype("<u2").view(np.uint8).reshape(-1, 2)
    return image


_RNG = np.random.default_rng(40)
_ROWS = np.arange(AZIMUTHS)
DEGENERATE_HEADERS = {
    "angles all equal": (None, np.full(AZIMUTHS, 100), "encoder_one_turn"),
    "angles reversed": (None, (13 + 14 * _ROWS)[::-1], "encoder_one_turn"),
    "angles random": (None, _RNG.integers(0, 5600, AZIMUTHS), "encoder_one_turn"),
    "angles over two turns": (None, (13 + 28 * _ROWS) % 5600, "encoder_one_turn"),
    "times all equal": (np.full(AZIMUTHS, START_US), None, "azimuth_time_increasing"),
    "times at INT64_MAX": (np.full(AZIMUTHS, np.iinfo(np.int64).max), None, "azimuth_time_range"),
    "times negative": (-START_US + 625 * _ROWS, None, "azimuth_time_range"),
    "times overflowing their differences": (
        np.where(_ROWS < 200, -(2**62), 2**62),
        None,
        "azimuth_time_range",
    ),
    "a sweep of 0.4 ms": (START_US + _ROWS, None, "sweep_period"),
    "a sweep of 10 s": (START_US + 25_000 * _ROWS, None, "sweep_period"),
}


@pytest.mark.parametrize("case", sorted(DEGENERATE_HEADERS))
def test_a_degenerate_header_is_refused_naming_its_rule(case: str):
    times, encoder, rule = DEGENERATE_HEADERS[case]
    image = _with_header(native_png(3768, [(30.0, 20.0)], 0.0432), times, encoder)
    with pytest.raises(ValueError, match=f"rule {rule}"):
        parse_native_scan(image)


def test_a_real_sensors_header_passes_the_rules():
    """The rules accept the layouts the datasets write: wrapping once through 0, and a wobbling Boreas encoder."""
    wrapped = (5000 + 14 * _ROWS) % 5600  # starts late in the turn and wraps through 0
    scan = parse_native_scan(_with_header(native_png(3768, [], 0.0432), encoder=wrapped))
    assert np.all(np.diff(scan.azimuths) > 0)
    wobble = _RNG.integers(-5, 6, AZIMUTHS)
    wobble[0], wobble[-1] = 0, min(0, wobble[-1])
    parse_native_scan(native_png(3360, [], 0.0596, wobble=wobble), "boreas")


def test_unmeasured_azimuths_do_not_reach_the_converted_scan():
    """The valid flag is honoured: a return only on azimuths flagged not measured is not in the converted scan, and
    the same return on measured azimuths is; a scan with fewer than half its azimuths measured is refused."""
    image = native_png(3768, [(90.0, 40.0)], 0.0432)
    bright_rows = np.flatnonzero(image[:, HEADER_COLUMNS:].max(axis=1) > 0)
    assert bright_rows.size == 3
    measured = to_cartesian(parse_native_scan(image))
    unmeasured = image.copy()
    unmeasured[bright_rows, 10] = 0
    converted = to_cartesian(parse_native_scan(unmeasured))
    assert measured.max() > 100 and converted.max() < 10
    mostly_invalid = image.copy()
    mostly_invalid[: AZIMUTHS // 2 + 1, 10] = 0
    with pytest.raises(ValueError, match="rule valid_azimuths"):
        parse_native_scan(mostly_invalid)


def test_the_native_shape_is_bounded_by_the_sensors():
    """Oxford's and Boreas' sizes pass; columns or rows beyond the documented sensors' do not, unless allowed."""
    from rafd.scans.native import NativeShape

    assert is_native_shape(11 + 3768, 400) and is_native_shape(11 + 6848, 400)
    assert not is_native_shape(400_000, 400) and not is_native_shape(11 + 6849, 400)
    assert not is_native_shape(11 + 3768, 401) and not is_native_shape(11 + 3768, 99)
    assert is_native_shape(11 + 8000, 800, NativeShape(max_azimuths=800, max_range_bins=8000))


# ---------------------------------------------------------------- Boreas-RT: a Doppler-mode chirp column (issue 60)
def test_a_chirp_column_is_named_boreas_rt_and_not_read_as_validity():
    """Column 10 alternating 0 / 255 is a RAS6's chirp flag: the scan is read as boreas-rt, every azimuth measured,
    so a return on a "0" azimuth reaches the converted scan (read as a valid flag it would be dropped)."""
    image = native_png(6848, [(90.0, 40.0)], 0.04381)
    image[:, 10] = np.where(np.arange(AZIMUTHS) % 2, 255, 0)
    assert native_format_name(image.shape[1], image[:, 10]) == "boreas-rt"
    scan = parse_native_scan(image, native_format_name(image.shape[1], image[:, 10]))
    assert scan.fmt.name == "boreas-rt" and scan.fmt.flag_column == "chirp" and scan.valid.all()
    np.testing.assert_allclose(brightest_metres(to_cartesian(scan)), [40.0, 0.0], atol=0.6)
    as_valid_flag = parse_native_scan(image, "boreas")  # the old reading: half the azimuths unmeasured
    assert as_valid_flag.valid.sum() == AZIMUTHS // 2
    # An Oxford valid flag with a few unmeasured azimuths does not alternate: still a valid flag.
    oxford = native_png(3768, [], 0.0432)
    oxford[[5, 9, 200], 10] = 0
    assert native_format_name(oxford.shape[1], oxford[:, 10]) == "oxford"


def test_the_real_boreas_rt_scan_reads_as_boreas_rt(boreas_rt_scan: Path):
    """The real RAS6 Doppler scan: its column 10 alternates, so it is named boreas-rt, 6848 bins of 0.04381 m, every
    one of its 400 azimuths measured (read as a valid flag only 200 were); its sweep is one 4 Hz turn."""
    image = cv2.imread(str(boreas_rt_scan), cv2.IMREAD_UNCHANGED)
    name = native_format_name(image.shape[1], image[:, 10])
    assert name == "boreas-rt"
    scan = read_native_scan(boreas_rt_scan, name)
    assert scan.range_bins == 6848 and scan.fmt.range_bin_m == pytest.approx(0.04381)
    assert scan.valid.all() and int((image[:, 10] == 255).sum()) == 200
    assert scan.timestamp_us == int(boreas_rt_scan.stem)
    assert 0.24 < (scan.timestamps_us[-1] - scan.timestamps_us[0]) / 1e6 < 0.26
    converted = to_cartesian(scan)
    assert converted.shape == (1152, 1152) and converted.mean() > 1.0  # a real scene, not an empty disc


def test_a_known_range_bin_replaces_the_formats():
    fmt = NATIVE_FORMATS["oxford"].with_range_bin(0.0864)
    assert fmt.name == "oxford" and fmt.range_bin_m == 0.0864
    assert NATIVE_FORMATS["oxford"].with_range_bin(None) is NATIVE_FORMATS["oxford"]
    with pytest.raises(ValueError, match="positive"):
        NATIVE_FORMATS["oxford"].with_range_bin(0.0)
