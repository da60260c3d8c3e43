"""tools.compare_steps: both models are timed on every runtime installed and the ratio is printed; bad paths refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from tools.compare_steps import compare, main


def test_the_shipped_step_against_itself_is_timed_on_each_runtime(capsys) -> None:
    pytest.importorskip("onnxruntime")
    from rafd.assets import default_onnx

    onnx = default_onnx()
    result = compare(onnx, onnx, rounds=2)
    assert "onnxruntime" in result and all(old > 0 and new > 0 for old, new in result.values())
    assert main([str(onnx), str(onnx), "--rounds", "2"]) == 0
    assert "new / old" in capsys.readouterr().out


def test_a_missing_model_is_refused(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "a.onnx"), str(tmp_path / "b.onnx")])
    assert exit_info.value.code == 2 and "is not a file" in capsys.readouterr().err
