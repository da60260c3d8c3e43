"""rafd-polar: the conventions fit recovers known offsets; the comparison and conversion on the real sample."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.cli.polar import fit_conventions, main
from rafd.scans.polar import PolarConventions, polar_to_cartesian


def test_fit_recovers_the_conventions_that_made_an_image():
    rng = np.random.default_rng(11)
    polar = cv2.GaussianBlur(rng.uniform(0, 255, (128, 400)).astype(np.float32), (0, 0), 1.5)  # [R, A]
    truth = PolarConventions(azimuth_offset=0.3, range_offset=0.1, centre_offset=(0.5, -0.25))
    reference = polar_to_cartesian(polar, 256, conventions=truth)
    fitted = fit_conventions(polar, reference)
    assert abs(fitted.azimuth_offset - 0.3) < 0.05 and abs(fitted.range_offset - 0.1) < 0.05
    assert np.allclose(fitted.centre_offset, (0.5, -0.25), atol=0.05)


def _polar_folder(tmp_path: Path, polar: np.ndarray) -> Path:
    folder = tmp_path / "polar_seq"
    (folder / "Navtech_Polar").mkdir(parents=True)
    cv2.imwrite(str(folder / "Navtech_Polar" / "000001.png"), polar)
    (folder / "Navtech_Polar.txt").write_text("Frame: 000001 Time: 1574859771.744660272\n")
    return folder


def test_writes_the_converted_scans(tmp_path: Path, capsys: pytest.CaptureFixture):
    polar = np.full((576, 400), 90, np.uint8)
    folder = _polar_folder(tmp_path, polar)
    assert main([str(folder), "--out", str(tmp_path / "out"), "--repeats", "2"]) == 0
    scan = cv2.imread(str(tmp_path / "out" / "Navtech_Cartesian" / "000001.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(scan, polar_to_cartesian(polar))
    assert (tmp_path / "out" / "Navtech_Cartesian.txt").read_text().startswith("Frame: 000001")
    assert "median" in capsys.readouterr().out


def test_bad_input_exits_2_with_the_reason(tmp_path: Path, capsys: pytest.CaptureFixture):
    assert main([str(tmp_path / "nowhere")]) == 2
    assert "Navtech_Polar.txt" in capsys.readouterr().err
    folder = _polar_folder(tmp_path, np.zeros((576, 400), np.uint8))
    assert main([str(folder), "--fit"]) == 2
    assert "--compare" in capsys.readouterr().err
    assert main([str(folder), "--compare", str(tmp_path / "nowhere")]) == 2
    assert "not found" in capsys.readouterr().err


def test_compares_with_radiates_images(radiate_polar_sample: Path, radiate_sample: Path, capsys: pytest.CaptureFixture):
    assert main([str(radiate_polar_sample), "--compare", str(radiate_sample), "--repeats", "2"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.split()[:1] in (["1"], ["2"])]
    radiate = {int(r[0]): (float(r[2]), float(r[3])) for r in rows if r[1] == "radiate"}
    assert set(radiate) == {1, 2} and all(mad < 3.5 and corr > 0.97 for mad, corr in radiate.values())
