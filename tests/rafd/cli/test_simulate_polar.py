"""rafd-simulate --polar writes RADIATE's Navtech_Polar beside the Cartesian scans; without it, nothing polar."""

from __future__ import annotations

from pathlib import Path

import cv2

from rafd.cli.simulate import main


def test_polar_flag_writes_navtech_polar(tmp_path: Path) -> None:
    assert (
        main(["--out", str(tmp_path / "out"), "--sequence-frames", "2", "--seed", "5", "--scan-size", "128", "--polar"])
        == 0
    )
    folder = tmp_path / "out" / "sim_5_0"
    polar = cv2.imread(str(folder / "Navtech_Polar" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert polar.shape == (576, 400) and polar.dtype.name == "uint8" and polar[:20].mean() > 0
    assert (folder / "Navtech_Polar.txt").read_text() == (folder / "Navtech_Cartesian.txt").read_text()
    assert main(["--out", str(tmp_path / "plain"), "--sequence-frames", "1", "--scan-size", "64"]) == 0
    assert not (tmp_path / "plain" / "sim_0_0" / "Navtech_Polar").exists()
