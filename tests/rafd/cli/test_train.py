"""rafd-train: a tiny run writes its files; bad data roots and splits fail with a clear message."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rafd.cli.train import main
from rafd.train.trainer import history_path, optimizer_state_path


def test_tiny_run_writes_checkpoint_optimizer_state_and_history(trained_checkpoint: Path) -> None:
    from rafd.model.checkpoint import load_checkpoint

    assert optimizer_state_path(trained_checkpoint).is_file()
    history = json.loads(history_path(trained_checkpoint).read_text())
    assert len(history) == 1 and history[0]["step"] == 2 and history[0]["loss_total"] > 0
    _, cfg, _ = load_checkpoint(trained_checkpoint, map_location="cpu")
    assert (cfg.num_frames, cfg.input_size) == (2, 64)


def test_ablation_flags_reach_the_model_config(sim_root: Path, tmp_path: Path) -> None:
    from rafd.model.checkpoint import load_checkpoint

    out = tmp_path / "ablation.pt"
    argv = [
        str(sim_root),
        "--split",
        "train",
        "--window-frames",
        "2",
        "--input-size",
        "64",
        "--out",
        str(out),
        "--epochs",
        "1",
        "--batch-size",
        "2",
        "--max-steps-per-epoch",
        "1",
        "--device",
        "cpu",
        "--quiet",
        "--no-enhancement",
        "--no-flow-guidance",
        "--no-flow-supervision",
    ]
    assert main(argv) == 0
    _, cfg, meta = load_checkpoint(out, map_location="cpu")
    assert cfg.enhance.enabled is False and cfg.propagation.flow_guided is False
    assert meta["loss_config"]["flow_weight"] == 0.0


def test_missing_data_root_fails_clearly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nowhere"
    assert main([str(missing), "--split", "train", "--out", str(tmp_path / "m.pt")]) != 0
    err = capsys.readouterr().err
    assert "does not exist" in err and str(missing) in err
    assert not (tmp_path / "m.pt").exists()


def test_split_without_sequences_fails_clearly(
    sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(sim_root), "--split", "no_such_split", "--out", str(tmp_path / "m.pt")]) != 0
    err = capsys.readouterr().err
    assert "no_such_split" in err


def test_missing_resume_checkpoint_fails_clearly(
    sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [
        str(sim_root),
        "--split",
        "train",
        "--out",
        str(tmp_path / "x.pt"),
        "--resume",
    ]
    assert main(argv) != 0
    assert "x.pt" in capsys.readouterr().err


def test_init_and_resume_together_are_refused(
    sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    some = tmp_path / "some.pt"
    some.write_bytes(b"x")
    argv = [
        str(sim_root),
        "--split",
        "train",
        "--out",
        str(some),
        "--init",
        str(some),
        "--resume",
    ]
    assert main(argv) != 0
    assert "--init" in capsys.readouterr().err
    argv = [
        str(sim_root),
        "--split",
        "train",
        "--out",
        str(tmp_path / "m.pt"),
        "--init",
        str(tmp_path / "no.pt"),
    ]
    assert main(argv) != 0
    assert "no.pt" in capsys.readouterr().err


def test_propagation_norm_flag_reaches_the_model_config(sim_root: Path, tmp_path: Path) -> None:
    from rafd.model.checkpoint import load_checkpoint

    out = tmp_path / "post.pt"
    argv = [
        str(sim_root),
        "--split",
        "train",
        "--config",
        "default",
        "--window-frames",
        "2",
        "--input-size",
        "64",
        "--out",
        str(out),
        "--epochs",
        "1",
        "--batch-size",
        "2",
        "--max-steps-per-epoch",
        "1",
        "--device",
        "cpu",
        "--quiet",
        "--no-augment",
        "--propagation-norm",
        "post",
    ]
    assert main(argv) == 0
    _, cfg, _ = load_checkpoint(out, map_location="cpu")
    assert cfg.propagation.norm == "post"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--mix-split", "train"], "--mix-split and --mix-cache describe --mix-data"),
        (["--mix-data", "ROOT", "--mix-share", "1"], "--mix-share is the share"),
        (["--no-augment", "--max-rotation-deg", "90"], "--no-augment contradicts"),
    ],
)
def test_mix_and_augmentation_flags_that_contradict_fail_clearly(
    sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    argv = [str(sim_root), "--split", "train", "--out", str(tmp_path / "m.pt"), "--device", "cpu", "--quiet"]
    assert main(argv + [str(sim_root) if a == "ROOT" else a for a in extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "m.pt").exists()
