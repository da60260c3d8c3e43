"""Checkpoints: exact round trip, clear CheckpointError for every kind of bad file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from rafd.model import build_model
from rafd.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint


@pytest.fixture
def saved(tmp_path: Path, make_config) -> tuple[Path, torch.nn.Module]:
    cfg = make_config(2)
    model = build_model(cfg)
    with torch.no_grad():  # non-default BN statistics too (the persistent buffers)
        for name, value in model.state_dict().items():
            if "running" in name:
                value.add_(0.1)
    path = tmp_path / "sub" / "model.pt"
    save_checkpoint(path, model, cfg, meta={"epoch": 3, "note": "x"})
    return path, model


def test_round_trip_reproduces_outputs_exactly(saved, make_inputs) -> None:
    path, model = saved
    loaded, cfg, meta = load_checkpoint(path)
    assert meta == {"epoch": 3, "note": "x"} and cfg.num_frames == 2 and not loaded.training
    model.eval()
    frames, poses = make_inputs(cfg, 2)
    with torch.no_grad():
        expected, got = model(frames, poses), loaded(frames, poses)
    for name in expected:
        assert torch.equal(expected[name], got[name]), name
    # weights_only-safe: plain tensors and strings
    payload = torch.load(path, weights_only=True)
    assert set(payload) == {"state_dict", "config", "version", "meta"}
    assert not list(path.parent.glob("*.tmp"))  # the atomic write left no temp file behind


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.pt"
    with pytest.raises(CheckpointError, match="nope.pt"):
        load_checkpoint(path)


def test_garbage_bytes(tmp_path: Path) -> None:
    path = tmp_path / "garbage.pt"
    path.write_bytes(b"\x00\x01 definitely not a torch file" * 10)
    with pytest.raises(CheckpointError, match="garbage.pt"):
        load_checkpoint(path)


def test_truncated_file(saved, tmp_path: Path) -> None:
    path, _ = saved
    cut = tmp_path / "cut.pt"
    cut.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(CheckpointError, match="cut.pt"):
        load_checkpoint(cut)


@pytest.mark.parametrize("content", [{"weights": torch.zeros(3)}, torch.zeros(3)])
def test_foreign_torch_file(tmp_path: Path, content) -> None:
    path = tmp_path / "foreign.pt"
    torch.save(content, path)
    with pytest.raises(CheckpointError, match="foreign.pt.*not an RaFD checkpoint"):
        load_checkpoint(path)


def test_invalid_config_json(saved, tmp_path: Path) -> None:
    path, _ = saved
    payload = torch.load(path, weights_only=True)
    payload["config"] = "{not json"
    bad = tmp_path / "badcfg.pt"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match="badcfg.pt.*config"):
        load_checkpoint(bad)


def test_state_dict_that_does_not_fit_the_config(saved, tmp_path: Path) -> None:
    path, _ = saved
    payload = torch.load(path, weights_only=True)
    config = json.loads(payload["config"])
    config["neck"]["channels"] = 16  # a different width than the stored weights
    payload["config"] = json.dumps(config)
    bad = tmp_path / "mismatch.pt"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match="mismatch.pt.*state_dict"):
        load_checkpoint(bad)
    payload = torch.load(path, weights_only=True)
    payload["state_dict"].pop(next(iter(payload["state_dict"])))
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match="mismatch.pt"):
        load_checkpoint(bad)
