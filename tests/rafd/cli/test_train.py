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


# a run as short as one can be: 2 frames of 64 px, one step of 2 windows, on the CPU
SHORT = [
    "model.num_frames=2",
    "model.input_size=64",
    "train.epochs=1",
    "train.batch_size=2",
    "train.max_steps_per_epoch=1",
    "train.device=cpu",
]


def test_ablation_settings_reach_the_config_the_checkpoint_stores(sim_root: Path, tmp_path: Path) -> None:
    from rafd.model.checkpoint import load_checkpoint
    from rafd.train.config import RunConfig

    out = tmp_path / "ablation.pt"
    argv = [str(sim_root), "--split", "train", "--out", str(out), "--quiet", *SHORT]
    ablations = ["model.enhance.enabled=false", "model.propagation.flow_guided=false", "loss.flow_weight=0"]
    assert main([*argv, *ablations]) == 0
    _, cfg, meta = load_checkpoint(out, map_location="cpu")
    assert cfg.enhance.enabled is False and cfg.propagation.flow_guided is False
    stored = RunConfig.from_dict(meta["run_config"])  # the whole config, rebuilt from the checkpoint alone
    assert stored.loss.flow_weight == 0.0 and stored.model == cfg and meta["recipe"] == "tiny"


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


def test_the_flow_modules_settings_reach_the_model(sim_root: Path, tmp_path: Path) -> None:
    """flow.local_radius and flow.channels, which no flag set before the one config, and a recipe's own settings
    overridden after it."""
    from rafd.model.checkpoint import load_checkpoint

    out = tmp_path / "flow.pt"
    argv = [str(sim_root), "--split", "train", "--config", "cpu", "--out", str(out), "--quiet", *SHORT]
    settings = ["model.flow.local_radius=2", "model.flow.channels=4", "model.propagation.norm=post"]
    assert main([*argv, "data.augment.enabled=false", *settings]) == 0
    _, cfg, _ = load_checkpoint(out, map_location="cpu")
    assert (cfg.flow.local_radius, cfg.flow.channels, cfg.propagation.norm) == (2, 4, "post")
    assert cfg.propagation.mode == "joint"  # the cpu recipe's


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--mix-split", "train"], "--mix-split and --mix-cache describe --mix-data"),
        (["--mix-data", "ROOT", "data.mix_share=1"], "data.mix_share is a share"),
        (["train.lr=fast"], "train.lr takes float"),
        (["model.flow.radius=2"], "did you mean model.flow.local_radius"),
        (["ROOT"], "one data root"),
    ],
)
def test_settings_and_flags_that_cannot_hold_fail_clearly(
    sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    argv = [str(sim_root), "--split", "train", "--out", str(tmp_path / "m.pt"), "--quiet", "train.device=cpu"]
    with pytest.raises(SystemExit) as exit_info:
        main(argv + [str(sim_root) if a == "ROOT" else a for a in extra])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "m.pt").exists()
