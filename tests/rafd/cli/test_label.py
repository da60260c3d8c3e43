"""rafd-label on a native folder written here: candidates and sheets, box text -> label file, agreement of two label
files (found / missed / extra / in ignore), and a linked, labelled folder that the datasets read."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rafd.cli.label import agreement, main
from rafd.data import read_sequence
from tests.rafd.data.test_native_folder import STAMPS, write_folder
from tests.rafd.scans.test_native import native_png


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    root = write_folder(tmp_path / "seq", STAMPS[:3])
    for k, stamp in enumerate(STAMPS[:3]):  # a car-sized return ahead-right, moving 1 m per scan
        import cv2

        image = native_png(3768, [(30.0, 12.0 + k), (300.0, 15.0)], 0.0432, start_us=stamp, size_m=3.0)
        cv2.imwrite(str(root / "radar" / f"{stamp}.png"), image)
    return root


def test_propose_writes_an_overview_sheets_and_an_editable_box_list(folder: Path, tmp_path: Path):
    out = tmp_path / "proposals"
    assert main(["propose", str(folder), "--out", str(out), "--frame-numbers", "2", "--radius", "30"]) == 0
    assert (out / "000002_overview.png").is_file()
    lines = [line for line in (out / "000002_candidates.txt").read_text().splitlines() if not line.startswith("#")]
    assert lines and all(line.startswith(str(STAMPS[1])) for line in lines)
    assert len(list(out.glob("000002_c*.png"))) == len(lines)


def test_apply_compare_and_link(
    folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
):
    import tempfile

    scratch = tmp_path / "scratch"  # where compare and render link their labelled folders for a while
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    ours = tmp_path / "ours.txt"
    ours.write_text(
        f"{STAMPS[0]} 1 car 6.0 10.4 2.0 4.5 -30\n{STAMPS[1]} 1 car 6.5 11.3 2.0 4.5 -30\n"
        f"{STAMPS[1]} 9 ignore -13.0 7.5 4.0 4.0 0\n"
    )
    theirs = tmp_path / "theirs.txt"
    theirs.write_text(
        f"{STAMPS[0]} 5 car 6.3 10.0 2.0 4.5 -30\n{STAMPS[1]} 6 car -13.0 7.5 2.0 4.5 0\n"
        f"{STAMPS[2]} 7 car 0.0 -20.0 2.0 4.5 0\n"
    )
    assert main(["apply", str(folder), str(ours), "--out", str(tmp_path / "ours.json")]) == 0
    assert main(["apply", str(folder), str(theirs), "--out", str(tmp_path / "theirs.json")]) == 0
    capsys.readouterr()
    assert main(["compare", str(tmp_path / "theirs.json"), str(tmp_path / "ours.json"), str(folder)]) == 0
    result = json.loads(capsys.readouterr().out)
    # theirs: frame 1 found (0.5 m), frame 2's car lies in our ignore region, frame 3's is missed; our frame-2 car extra
    assert (result["found"], result["in_ignore"], result["missed"], result["extra"]) == (1, 1, 1, 1)
    assert result["centre_distance_mean_m"] == pytest.approx(0.5, abs=0.01) and 0.5 < result["iou_mean"] <= 1.0
    assert main(["render", str(folder), str(tmp_path / "ours.json"), "--out", str(tmp_path / "drawn"), "--quiet"]) == 0
    assert len(list((tmp_path / "drawn").glob("*_labels.png"))) == 2
    assert not list(scratch.iterdir())  # nothing left behind
    linked = tmp_path / "root" / "seq_train"
    assert (
        main(
            [
                "link",
                str(folder),
                str(tmp_path / "ours.json"),
                str(linked),
                "--split",
                "train",
                "--frame-numbers",
                "1-2",
            ]
        )
        == 0
    )
    sequence = read_sequence(linked, estimate_poses=False)
    assert sequence.split == "train" and len(sequence) == 2
    # the labelled boxes, and the scan outside the protocol's 30 m square as 4 ignore regions (--labelled-half-m)
    labelled = [[o for o in f.objects if o.id >= 0] for f in sequence.frames]
    assert [len(objects) for objects in labelled] == [1, 2]
    assert all(sum(o.id < 0 and o.class_name == "ignore" for o in f.objects) == 4 for f in sequence.frames)
    bad = tmp_path / "bad.txt"
    bad.write_text("123 1 car 1 1 2 4 0\n")
    assert main(["apply", str(folder), str(bad), "--out", str(tmp_path / "bad.json")]) == 2
    assert "no scan of" in capsys.readouterr().err


def test_agreement_counts():
    import numpy as np

    reference = [np.array([[0.0, 10.0, 2, 4.5, 0], [10.0, 0.0, 2, 4.5, 0]])]
    candidate = [np.array([[0.5, 10.0, 2, 4.5, 0], [-20.0, 0.0, 2, 4.5, 0]])]
    result = agreement(reference, candidate, [np.array([[10.0, 0.0, 3, 3, 0]])])
    assert (result["found"], result["missed"], result["in_ignore"], result["extra"]) == (1, 0, 1, 1)
