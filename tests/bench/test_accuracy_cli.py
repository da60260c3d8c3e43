"""rafd bench accuracy: a scaled-down benchmark simulates, trains two variants and writes the tables."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.accuracy import BENCHMARK_SPLITS
from bench.accuracy_cli import main


@pytest.mark.slow
def test_small_benchmark_end_to_end(tmp_path: Path) -> None:
    data = tmp_path / "bench"
    assert main(["data", "--out", str(data), "--scale", "0.25", "--sequence-frames", "5"]) == 0
    manifest = json.loads((data / "benchmark.json").read_text())
    assert [s["split"] for s in manifest["splits"]] == [s.split for s in BENCHMARK_SPLITS]
    assert [s["seed"] for s in manifest["splits"]] == [s.seed for s in BENCHMARK_SPLITS]
    out = tmp_path / "run"
    code = main(
        [
            "run",
            str(data),
            "--out",
            str(out),
            "--variants",
            "rafd2,single",
            "--epochs",
            "1",
            "--max-steps-per-epoch",
            "1",
            "--batch-size",
            "2",
            "--device",
            "cpu",
        ]
    )
    assert code == 0
    results = json.loads((out / "results.json").read_text())
    assert [r["variant"] for r in results["rows"]] == ["rafd2", "single"]
    assert all(0.0 <= r["mAP@0.5"] <= 100.0 for r in results["rows"])
    assert results["rows"][1]["epe_all"] is None  # single frame: no flow
    assert (out / "results.md").read_text().count("\n") == 4
    # paired bootstrap between two variants of the run (both scored on the same frames)
    assert (
        main(["compare", str(out / "single"), str(out / "rafd2"), "--resamples", "20", "--json", str(out / "cmp.json")])
        == 0
    )
    comparison = json.loads((out / "cmp.json").read_text())
    assert comparison["frames"] == results["rows"][0]["frames"]
    assert set(comparison["metrics"]) >= {"mAP@0.5", "centre_AP"}
    row = comparison["metrics"]["mAP@0.5"]
    assert row["difference"] == pytest.approx(results["rows"][0]["mAP@0.5"] - results["rows"][1]["mAP@0.5"])
    assert row["low"] <= row["high"]
    # second stage of the two-stage recipe: starts from `single` in the same out_dir, rows of the first run kept
    code = main(
        [
            "run",
            str(data),
            "--out",
            str(out),
            "--variants",
            "rafd4_from_single",
            "--epochs",
            "1",
            "--max-steps-per-epoch",
            "1",
            "--batch-size",
            "2",
            "--device",
            "cpu",
        ]
    )
    assert code == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [(r["variant"], r["init"]) for r in rows] == [
        ("rafd2", None),
        ("single", None),
        ("rafd4_from_single", "single"),
    ]
    from rafd.model.checkpoint import read_checkpoint

    _, cfg, meta = read_checkpoint(out / "rafd4_from_single" / "model.pt")
    assert cfg.num_frames == 4 and cfg.propagation.norm == "pre"
    assert meta["init"] == str(out / "single" / "model.pt")
    # a run stopped after epoch 1 of 2 goes on from there with --resume: one more epoch, not two, provenance kept
    history = out / "rafd4_from_single" / "model.pt.history.json"
    first = json.loads(history.read_text())
    code = main(
        [
            "run",
            str(data),
            "--out",
            str(out),
            "--variants",
            "rafd4_from_single",
            "--epochs",
            "2",
            "--resume",
            "--max-steps-per-epoch",
            "1",
            "--batch-size",
            "2",
            "--device",
            "cpu",
        ]
    )
    assert code == 0
    epochs = json.loads(history.read_text())
    assert [e["epoch"] for e in epochs] == [1, 2] and epochs[0] == first[0]  # epoch 1 was not trained again
    row = json.loads((out / "results.json").read_text())["rows"][-1]
    assert row["variant"] == "rafd4_from_single" and row["resumed"]
    assert row["train_seconds"] == pytest.approx(sum(e["seconds"] for e in epochs))
    _, _, meta = read_checkpoint(out / "rafd4_from_single" / "model.pt")
    assert meta["epoch"] == 2 and meta["init"] == str(out / "single" / "model.pt")
    # a finished run is only evaluated again
    assert (
        main(
            [
                "run",
                str(data),
                "--out",
                str(out),
                "--variants",
                "rafd4_from_single",
                "--epochs",
                "2",
                "--resume",
                "--max-steps-per-epoch",
                "1",
                "--batch-size",
                "2",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    assert json.loads(history.read_text()) == epochs


def test_compare_needs_detections(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["compare", str(tmp_path), str(tmp_path / "b.npz")]) == 2
    assert "test_detections.npz does not exist" in capsys.readouterr().err


def test_run_without_manifest_and_unknown_variant_fail(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o")]) != 0
    assert "benchmark.json" in capsys.readouterr().err
    (tmp_path / "benchmark.json").write_text(
        json.dumps({"input_size": 64, "train_split": "train", "test_split": "test"})
    )
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--variants", "rafd4_from_single"]) != 0
    err = capsys.readouterr().err
    assert "train variant single" in err and str(tmp_path / "o" / "single" / "model.pt") in err
