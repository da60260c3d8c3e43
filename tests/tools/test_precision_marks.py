"""tools.precision_marks on the shipped model: where OpenVINO runs bf16 it prints each mark's runtime precisions and
a verdict; elsewhere it refuses, saying why (exit 2)."""

from __future__ import annotations

import pytest

from rafd.runtime.openvino_backend import openvino_supports_bf16
from tools import precision_marks

pytest.importorskip("openvino")


def test_each_mark_is_compiled_and_judged_against_the_unmarked_model(capsys):
    status = precision_marks.main(["--marks", "precise_0"])
    captured = capsys.readouterr()
    if not openvino_supports_bf16():
        assert status == 2 and "no bf16 that OpenVINO runs" in captured.err
        return
    assert status == 0
    lines = captured.out.splitlines()
    assert lines[1].startswith("unmarked: ") and "Convolution bf16: " in lines[1]  # bf16 really reaches the convs
    assert lines[2].startswith("precise_0: ") and ("(changed)" in lines[2] or "not honoured" in lines[2])


def test_a_missing_model_is_refused(tmp_path):
    if not openvino_supports_bf16():
        pytest.skip("this CPU has no bf16 OpenVINO runs: the command refuses before reading the model")
    with pytest.raises(SystemExit):
        precision_marks.main([str(tmp_path / "missing.onnx")])
