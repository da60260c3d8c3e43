"""rafd-eval: metrics JSON (overall + per sequence) and plots; clear errors on bad input."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from rafd.cli.evaluate import main


def test_writes_metrics_json_and_plots(trained_checkpoint: Path, sim_root: Path, tmp_path: Path) -> None:
    out_json, plots = tmp_path / "metrics.json", tmp_path / "plots"
    code = main([str(trained_checkpoint), "--data", str(sim_root), "--split", "train", "--json", str(out_json),
                 "--plots", str(plots), "--examples", "2", "--device", "cpu", "--no-progress"])
    assert code == 0
    report = json.loads(out_json.read_text())
    overall = report["overall"]
    for key in ("mAP@0.3", "mAP@0.5", "mAP@0.7"):
        assert 0.0 <= overall[key] <= 100.0
    assert overall["epe_all"] is not None and overall["epe_all"] >= 0.0
    assert set(report["per_sequence"]) == {"sim_11_0", "sim_11_1"}
    assert sum(s["frames"] for s in report["per_sequence"].values()) == overall["frames"] > 0
    pngs = sorted(plots.glob("*.png"))
    assert plots / "precision_recall.png" in pngs
    examples = [p for p in pngs if p.name.startswith("example_")]
    assert len(examples) == 2
    image = cv2.imread(str(examples[0]))
    assert image is not None and image.ndim == 3


def test_bad_split_and_missing_checkpoint_fail_clearly(trained_checkpoint: Path, sim_root: Path, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(trained_checkpoint), "--data", str(sim_root), "--split", "nope", "--device", "cpu"]) != 0
    assert "nope" in capsys.readouterr().err
    assert main([str(tmp_path / "none.pt"), "--data", str(sim_root), "--split", "train"]) != 0
    assert "none.pt" in capsys.readouterr().err
