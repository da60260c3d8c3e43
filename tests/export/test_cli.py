"""rafd-export: a verified export, and clear refusals (bad checkpoints, unwritable outputs, failed parity)."""

from __future__ import annotations

import pytest

from export import verify
from export.cli import main
from rafd.runtime import OnnxRunner
from tests.utils.export_testing import make_checkpoint, small_config

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return make_checkpoint(tmp_path_factory.mktemp("cli") / "model.pt", small_config(2))


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_export_and_verify(checkpoint, tmp_path, capsys):
    output = tmp_path / "model.onnx"
    assert main([str(checkpoint), str(output)]) == 0
    out = capsys.readouterr().out
    assert "max abs" in out and "max rel" in out and "FAIL" not in out
    assert f"wrote {output}" in out and "verified" in out
    runner = OnnxRunner(output)
    assert runner.config == small_config(2) and runner.cache_names
    assert _leftovers(tmp_path) == []


def test_export_without_verification(checkpoint, tmp_path, capsys):
    output = tmp_path / "static.onnx"
    assert main([str(checkpoint), str(output), "--batch", "static", "--no-verify", "--opset", "18"]) == 0
    assert "not verified" in capsys.readouterr().out
    runner = OnnxRunner(output)
    assert runner.batch == 1 and runner.metadata["opset"] == "18"


def test_failed_parity_exits_non_zero_and_writes_nothing(checkpoint, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(verify.TOLERANCES, "heatmap", (0.0, 1e-12))  # float noise is now "beyond tolerance"
    output = tmp_path / "model.onnx"
    assert main([str(checkpoint), str(output)]) == 1
    captured = capsys.readouterr()
    assert "FAIL" in captured.out and "differ from PyTorch beyond tolerance" in captured.err
    assert not output.exists() and _leftovers(tmp_path) == []


def _foreign(path):
    torch.save({"weights": torch.zeros(3)}, path)


def _corrupt(path):
    path.write_bytes(b"\x80\x02 this is not a torch file")


def _truncated(path, source):
    path.write_bytes(source.read_bytes()[:1000])


def _mismatched(path):  # weights of the T = 4 network under a T = 1 config
    from rafd.model import build_model
    from rafd.model.checkpoint import save_checkpoint

    save_checkpoint(path, build_model(small_config(4)), small_config(1))


@pytest.mark.parametrize("kind", ["missing", "foreign", "corrupt", "truncated", "mismatched"])
def test_bad_checkpoints_are_refused(kind, checkpoint, tmp_path, capsys):
    bad = tmp_path / f"{kind}.pt"
    if kind == "foreign":
        _foreign(bad)
    elif kind == "corrupt":
        _corrupt(bad)
    elif kind == "truncated":
        _truncated(bad, checkpoint)
    elif kind == "mismatched":
        _mismatched(bad)
    output = tmp_path / "model.onnx"
    assert main([str(bad), str(output)]) == 1
    err = capsys.readouterr().err
    assert "bad checkpoint" in err and str(bad) in err
    assert not output.exists()


@pytest.mark.parametrize("kind", ["missing_folder", "folder_is_a_file", "output_is_a_folder"])
def test_unwritable_output_is_refused_before_the_export(kind, tmp_path, capsys):
    if kind == "missing_folder":
        output = tmp_path / "nowhere" / "model.onnx"
    elif kind == "folder_is_a_file":
        (tmp_path / "file").write_text("x")
        output = tmp_path / "file" / "model.onnx"
    else:
        output = tmp_path / "model.onnx"
        output.mkdir()
    # The checkpoint does not exist either: the output is checked first, before any (slow) work.
    assert main([str(tmp_path / "missing.pt"), str(output)]) == 1
    err = capsys.readouterr().err
    assert str(output.parent if kind != "output_is_a_folder" else output) in err and "bad checkpoint" not in err


def test_old_opset_is_a_usage_error(checkpoint, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([str(checkpoint), str(tmp_path / "model.onnx"), "--opset", "16"])
    assert exit_info.value.code == 2
    assert "opset must be >= 17" in capsys.readouterr().err


def test_an_onnx_model_given_as_the_checkpoint_is_named_as_such(tmp_path, capsys):
    """`rafd export model.onnx out.onnx`: the file is an ONNX model, not a checkpoint; no torch advice leaks."""
    from rafd.assets import default_onnx

    output = tmp_path / "out.onnx"
    assert main([str(default_onnx()), str(output)]) == 1
    err = capsys.readouterr().err
    assert "is an ONNX model, not a checkpoint" in err and "rafd train" in err
    for leak in ("weights_only", "file an issue", "torch.load", "Unpickl"):
        assert leak not in err, leak
    assert not output.exists()


def test_a_truncated_checkpoint_error_carries_no_library_advice(checkpoint, tmp_path, capsys):
    bad = tmp_path / "truncated.pt"
    _truncated(bad, checkpoint)
    assert main([str(bad), str(tmp_path / "m.onnx")]) == 1
    err = capsys.readouterr().err
    assert "not a readable RaFD checkpoint" in err and "weights_only" not in err and "file an issue" not in err
