"""create_runner: explicit choices, refusals, and "auto" (fastest measured choice; reduced precision only with a
passed accuracy gate)."""

from __future__ import annotations

import pytest

from rafd.runtime import create_runner, open_runner, runners, supported_choices


def _timer(times: dict[str, float]):
    seen = []

    def timer(runner) -> float:
        seen.append(f"{runner.runtime}/{runner.precision}")
        return times[seen[-1]]

    return timer, seen


def test_explicit_choices(shipped_onnx):
    runner = create_runner(shipped_onnx, "onnxruntime", "fp32", threads=1)
    assert (runner.runtime, runner.precision, runner.threads, runner.selection) == ("onnxruntime", "fp32", 1, {})
    assert runner.describe()["runtime"] == "onnxruntime"


@pytest.mark.parametrize(
    "runtime,precision,message",
    [
        ("onnxruntime", "bf16", "fp32 only"),
        ("tensorrt", "auto", "runtime must be"),
        ("auto", "int4", "precision must be"),
    ],
)
def test_impossible_choices_are_refused(shipped_onnx, runtime, precision, message):
    with pytest.raises(ValueError, match=message):
        create_runner(shipped_onnx, runtime, precision, threads=1)


def test_auto_keeps_the_fastest_and_records_the_timings(ungated_onnx):
    pytest.importorskip("openvino")
    timer, seen = _timer({"onnxruntime/fp32": 0.020, "openvino/fp32": 0.010, "openvino/bf16": 0.001})
    runner = create_runner(ungated_onnx, "auto", "auto", threads=1, timer=timer)
    # no gate recorded in the model's metadata: bf16 is never a candidate, however fast
    assert "openvino/bf16" not in seen
    assert (runner.runtime, runner.precision) == ("openvino", "fp32")
    assert runner.selection == {"onnxruntime/fp32": 20.0, "openvino/fp32": 10.0}


def test_auto_takes_bf16_only_with_a_passed_gate(gated_onnx):
    pytest.importorskip("openvino")
    if ("openvino", "bf16") not in supported_choices():
        pytest.skip("this CPU has no bf16")
    timer, seen = _timer({"onnxruntime/fp32": 0.020, "openvino/fp32": 0.010, "openvino/bf16": 0.005})
    runner = create_runner(gated_onnx, "auto", "auto", threads=1, timer=timer)
    assert (runner.runtime, runner.precision) == ("openvino", "bf16") and "openvino/bf16" in seen
    timer, _ = _timer({"onnxruntime/fp32": 0.001, "openvino/fp32": 0.010, "openvino/bf16": 0.005})
    assert create_runner(gated_onnx, "auto", "auto", threads=1, timer=timer).runtime == "onnxruntime"


def test_explicit_bf16_is_the_operators_choice(ungated_onnx, caplog):
    if ("openvino", "bf16") not in supported_choices():
        pytest.skip("this CPU has no bf16 or openvino is not installed")
    runner = create_runner(ungated_onnx, "openvino", "bf16", threads=1)
    assert runner.precision == "bf16"
    assert "without a passed accuracy gate" in caplog.text


def test_without_openvino_auto_falls_back_to_onnxruntime(shipped_onnx, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_openvino(name, *args, **kwargs):
        if name == "openvino" or name.startswith("openvino."):
            raise ImportError("no openvino here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_openvino)
    assert runners.supported_choices() == [("onnxruntime", "fp32")]
    runner = create_runner(shipped_onnx, threads=1)
    assert (runner.runtime, runner.precision) == ("onnxruntime", "fp32")
    with pytest.raises(ValueError, match="needs the `openvino` package"):
        open_runner(shipped_onnx, "openvino", "fp32", threads=1)


def test_auto_times_the_candidates_interleaved_and_keeps_each_ones_median(ungated_onnx):
    """A slow moment of a shared machine must not decide the choice: every round times each candidate once, and a
    single slow round of the fastest candidate does not lose it the choice."""
    pytest.importorskip("openvino")
    seen: list[str] = []
    slow_once = {"openvino/fp32": [0.010, 0.500, 0.011], "onnxruntime/fp32": [0.020, 0.021, 0.019]}

    def timer(runner) -> float:
        name = f"{runner.runtime}/{runner.precision}"
        seen.append(name)
        return slow_once[name][seen.count(name) - 1]

    runner = create_runner(ungated_onnx, "auto", "fp32", threads=1, timer=timer, rounds=3)
    assert seen == ["onnxruntime/fp32", "openvino/fp32"] * 3
    assert (runner.runtime, runner.selection) == ("openvino", {"onnxruntime/fp32": 20.0, "openvino/fp32": 11.0})
