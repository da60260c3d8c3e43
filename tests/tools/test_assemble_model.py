"""tools.assemble_model: a multi-frame model from a single-frame model's encoder + head and a multi-frame model's
flow branch + propagation."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from rafd.config import RaFDConfig
from rafd.model import build_model
from rafd.model.checkpoint import load_checkpoint, save_checkpoint
from tools.assemble_model import main


def _saved(path: Path, cfg: RaFDConfig, seed: int, meta: dict | None = None) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    model = build_model(cfg)
    save_checkpoint(path, model, cfg, meta=meta)
    return model.state_dict()


def test_the_parts_come_from_their_models(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    multi_cfg = RaFDConfig.tiny(input_size=64, num_frames=2)
    single = _saved(tmp_path / "s.pt", multi_cfg.replace(num_frames=1), 1, {"operating_threshold": 0.4, "note": "x"})
    multi = _saved(tmp_path / "m.pt", multi_cfg, 2)
    assert main([str(tmp_path / "s.pt"), str(tmp_path / "m.pt"), "--out", str(tmp_path / "a.pt")]) == 0
    model, cfg, meta = load_checkpoint(tmp_path / "a.pt")
    assert cfg == multi_cfg and meta["note"] == "x" and "operating_threshold" not in meta
    state = model.state_dict()
    for name, tensor in state.items():
        want = single[name] if name in single else multi[name]
        assert torch.equal(tensor, want), name
    assert any(name.startswith("flow.") for name in state) and any(name.startswith("encoder.") for name in single)
    assert f"{len(single)} tensors from" in capsys.readouterr().out


def test_other_networks_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _saved(tmp_path / "s.pt", RaFDConfig.tiny(input_size=64, num_frames=1), 1)
    _saved(tmp_path / "m.pt", RaFDConfig.tiny(input_size=128, num_frames=2), 2)
    assert main([str(tmp_path / "s.pt"), str(tmp_path / "m.pt"), "--out", str(tmp_path / "a.pt")]) == 2
    assert "not the same network" in capsys.readouterr().err and not (tmp_path / "a.pt").exists()
    assert main([str(tmp_path / "m.pt"), str(tmp_path / "m.pt"), "--out", str(tmp_path / "a.pt")]) == 2
    assert "must be a 1-frame model" in capsys.readouterr().err
