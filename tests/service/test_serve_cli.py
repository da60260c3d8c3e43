"""rafd-serve: argument handling up to the uvicorn call (which is replaced by a recorder)."""

from __future__ import annotations

import sys
import types

import pytest
import uvicorn

from service.cli import main
from service.http.head_limits import LimitedHttpToolsProtocol

pytestmark = pytest.mark.network


@pytest.fixture
def recorded(monkeypatch):
    calls = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **options: calls.append((app, options)))
    return calls


def test_serves_the_given_model_on_the_given_address(tmp_path, recorded):
    model = tmp_path / "model.onnx"
    model.write_bytes(b"onnx")
    assert main(["--model", str(model), "--host", "0.0.0.0", "--port", "9001", "--threads", "2"]) == 0
    ((app, options),) = recorded
    assert options["host"] == "0.0.0.0" and options["port"] == 9001
    assert app.state.settings.model_path == model and app.state.settings.threads == 2
    # the server rafd-serve runs (service/http/server.py): the service's HTTP protocol with its head limits, and a bound
    # on the graceful shutdown (issue 34 findings 1 and 8)
    assert issubclass(options["http"], LimitedHttpToolsProtocol)
    assert options["http"].limits.max_header_bytes == app.state.settings.max_header_bytes == 32 * 1024
    assert options["timeout_graceful_shutdown"] == app.state.settings.shutdown_timeout_s == 10.0


def test_missing_model_file_is_a_clear_error(tmp_path, recorded, capsys):
    assert main(["--model", str(tmp_path / "missing.onnx")]) == 2
    assert "missing.onnx" in capsys.readouterr().err
    assert not recorded


def test_without_model_uses_the_shipped_default(tmp_path, recorded, monkeypatch, capsys):
    shipped = tmp_path / "default.onnx"
    shipped.write_bytes(b"onnx")
    monkeypatch.delenv("RAFD_MODEL_PATH", raising=False)
    monkeypatch.setitem(sys.modules, "rafd.assets", types.SimpleNamespace(default_onnx=lambda: shipped))
    assert main([]) == 0
    assert recorded[0][0].state.settings.model_path == shipped

    def none_shipped():
        raise FileNotFoundError("no rafd/assets/*.onnx in this build")

    monkeypatch.setitem(sys.modules, "rafd.assets", types.SimpleNamespace(default_onnx=none_shipped))
    assert main([]) == 2
    assert "no default model" in capsys.readouterr().err


def test_a_checkpoint_given_as_the_model_is_named_as_such(recorded, capsys):
    from rafd.assets import default_checkpoint

    assert main(["--model", str(default_checkpoint())]) == 2
    err = capsys.readouterr().err
    assert "is a PyTorch checkpoint, not an ONNX model" in err and "rafd export" in err
    assert not recorded


def test_every_setting_is_a_flag_and_a_flag_wins_over_its_variable(tmp_path, recorded, monkeypatch, capsys):
    from service.cli import build_parser
    from service.settings import Settings

    parser = build_parser()
    options = {option for action in parser._actions for option in action.option_strings}
    for field in Settings.model_fields:
        assert "--" + field.replace("_", "-") in options, field
    helps = {action.dest: action.help for action in parser._actions}
    assert all(helps[f"setting_{field}"] for field in Settings.model_fields)
    descriptions = [field.description for field in Settings.model_fields.values()]
    assert all(descriptions) and len(set(descriptions)) == len(descriptions)  # each its own, in the field's metadata
    assert helps["setting_max_streams"].startswith(Settings.model_fields["max_streams"].description)
    assert "RAFD_MAX_STREAMS" in helps["setting_max_streams"] and "32" in helps["setting_max_streams"]
    assert "onnxruntime" not in helps["setting_threads"].split("[")[0].lower()  # the runtime-neutral meaning
    model = tmp_path / "model.onnx"
    model.write_bytes(b"\x08\x08\x12\x07pytorch")
    monkeypatch.setenv("RAFD_MAX_STREAMS", "7")
    monkeypatch.setenv("RAFD_STREAM_TTL_S", "9")
    argv = ["--model", str(model), "--max-streams", "3", "--score-threshold", "0.45", "--runtime", "onnxruntime"]
    assert main(argv) == 0
    settings = recorded[0][0].state.settings
    assert settings.max_streams == 3 and settings.stream_ttl_s == 9.0  # the flag wins; the variable still works
    assert settings.score_threshold == 0.45 and settings.runtime == "onnxruntime"
    assert main(["--model", str(model), "--max-streams", "0"]) == 2  # refused as the variable would be
    assert "max_streams" in capsys.readouterr().err
