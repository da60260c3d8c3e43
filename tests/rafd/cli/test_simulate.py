"""rafd-simulate CLI: success path, preview, and error exits."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest

from rafd.cli.simulate import main


def test_writes_sequences(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert (
        main(
            [
                "--out",
                str(tmp_path / "out"),
                "--sequences",
                "2",
                "--sequence-frames",
                "2",
                "--seed",
                "5",
                "--scan-size",
                "128",
                "--split",
                "test",
            ]
        )
        == 0
    )
    for k in range(2):
        image = cv2.imread(
            str(tmp_path / "out" / f"sim_5_{k}" / "Navtech_Cartesian" / "000002.png"), cv2.IMREAD_UNCHANGED
        )
        assert image.shape == (128, 128) and image.dtype.name == "uint8"
    assert "sim_5_1" in capsys.readouterr().out


def test_forced_weather_is_written(tmp_path: Path) -> None:
    import json

    assert (
        main(
            [
                "--out",
                str(tmp_path / "out"),
                "--sequences",
                "3",
                "--sequence-frames",
                "1",
                "--scan-size",
                "64",
                "--weather",
                "fog",
            ]
        )
        == 0
    )
    for k in range(3):
        meta = json.loads((tmp_path / "out" / f"sim_0_{k}" / "meta.json").read_text())
        assert meta["weather"] == "fog", meta


@pytest.mark.parametrize(
    "args, message",
    [
        (["--scan-size", "127"], "even"),
        (["--sequence-frames", "0"], "--sequence-frames"),
        (["--sequences", "0"], "--sequences"),
        (["--clutter", "-1"], "clutter"),
        (["--weather", "snow"], "--weather"),
    ],
)
def test_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str], message: str) -> None:
    try:
        code = main(["--out", str(tmp_path / "out"), *args])
    except SystemExit as exit_:  # argparse's own checks (choices)
        code = exit_.code
    assert code == 2
    assert message in capsys.readouterr().err


def test_out_dir_not_writable(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["--out", str(blocker / "out"), "--sequence-frames", "1", "--scan-size", "64"]) == 2
    assert "--out" in capsys.readouterr().err


def test_missing_out_dir_and_preview_without_sample(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert main([]) == 2
    monkeypatch.delenv("RAFD_RADIATE_SAMPLE", raising=False)
    assert main(["--preview", "--out", str(tmp_path / "p.png")]) == 2
    assert main(["--preview", "--out", str(tmp_path / "p.png"), "--sample", str(tmp_path)]) == 2
    assert "RADIATE sequence folder" in capsys.readouterr().err


def test_preview_side_by_side(tmp_path: Path, radiate_sample: Path) -> None:
    out = tmp_path / "preview.png"
    assert main(["--preview", "--out", str(out), "--sample", str(radiate_sample)]) == 0
    picture = cv2.imread(str(out))
    assert picture.shape == (768, 2 * 768 + 8, 3)
    red = (picture[..., 2] > 200) & (picture[..., 1] < 60)
    assert red[:, :768].sum() > 20  # the simulated scan's boxes
    assert red[:, 776:].sum() == 0  # the real scan without its labels (a frozen test set)
    assert picture[:, 776:].mean() > 5  # ... but with its image


@pytest.mark.slow
def test_realism_table_from_the_command_line(tmp_path: Path, radiate_sample: Path, capsys) -> None:
    import json

    from rafd.sim import simulate_dataset

    simulate_dataset(tmp_path / "sim", sequences=2, frames=2, seed=4, size=1152)
    out = tmp_path / "realism.json"
    assert (
        main(
            [
                "--realism",
                str(radiate_sample),
                "--realism-sim",
                str(tmp_path / "sim"),
                "--json",
                str(out),
                "--realism-steps",
                "20",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "18 real scans of tiny_foggy; 4 simulated scans" in printed and "patch classifier" in printed
    rows = json.loads(out.read_text())
    assert len(rows) == 9 and all(row["distance"] >= 0 for row in rows)
    assert any(row["name"].startswith("scan-to-scan") for row in rows)
    assert main(["--realism", str(radiate_sample), "--realism-sim", str(tmp_path / "sim"), "--weather", "fog"]) == 2
    assert "--weather" in capsys.readouterr().err
    simulate_dataset(tmp_path / "small", sequences=1, frames=2, seed=4, size=256)
    assert main(["--realism", str(radiate_sample), "--realism-sim", str(tmp_path / "small")]) == 2
    assert "1152 px" in capsys.readouterr().err
