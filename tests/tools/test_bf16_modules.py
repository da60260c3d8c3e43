"""tools.bf16_modules runs a small model with each module in bf16 and prints one row per variant."""

from __future__ import annotations

from pathlib import Path

from tests.utils.export_testing import make_checkpoint, small_config
from tools.bf16_modules import main


def test_one_row_per_module_and_the_kept_variant(tmp_path: Path, capsys):
    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(4))
    assert main([str(checkpoint), "--sequences", "1", "--sequence-frames", "5", "--keep-fp32", "propagation"]) == 0
    rows = [line.split()[0] for line in capsys.readouterr().out.splitlines()[3:]]
    assert rows[0] == "every" and rows[-1] == "all"
    assert {"encoder.normalise", "encoder.backbone", "flow", "propagation", "head"} <= set(rows)


def test_an_unknown_module_to_keep_is_refused(tmp_path: Path, capsys):
    import pytest

    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(4))
    with pytest.raises(SystemExit) as exit_info:
        main([str(checkpoint), "--sequence-frames", "5", "--sequences", "1", "--keep-fp32", "decoder"])
    assert exit_info.value.code == 2 and "--keep-fp32 takes modules" in capsys.readouterr().err
