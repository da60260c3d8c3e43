"""rafd-bench on the shipped model, model paths only (the HTTP path is exercised by the service tests): every
runtime and precision side by side, the matmul peaks, the concurrency comparison and the accuracy gate."""
from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from rafd.cli.bench import main, time_interleaved
from rafd.runtime import supported_choices


def test_bench_reports_every_runtime_side_by_side_and_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                  monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv("RAFD_RADIATE_SAMPLE", raising=False)  # simulated gate frames only: keeps the test short
    out = tmp_path / "bench.json"
    assert main(["--configs", "default", "--no-http", "--repeats", "2", "--threads", "1", "--concurrency-frames", "2",
                 "--gate-sequences", "1", "--gate-frames", "6", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    choices = [f"{r}/{p}" for r, p in supported_choices()]
    for path in ["pytorch eager, full window", "onnxruntime fp32, full window"] + [f"streaming step, {c}" for c in choices]:
        assert f"| default | {path} |" in table
    figures = json.loads(out.read_text())
    facts, machine = figures["facts"]["default"], figures["facts"]["machine"]
    assert facts["num_frames"] == 4 and facts["gflop_per_window"] > facts["gflop_per_step"] > 0
    assert facts["stream_state_bytes"] > 0 and set(facts["achieved_tflops_streaming"]) == set(choices)
    assert machine["matmul_peak_gflops"]["fp32"] > 0 and machine["matmul_peak_gflops"]["bf16"] > 0
    assert set(facts["concurrency"]) == {f"{c}, 1 concurrent run(s)" for c in choices}  # 1 thread: one mode
    reduced = [c for c in choices if not c.endswith("fp32")]
    assert set(facts["gate"]) == set(reduced)
    for gate in facts["gate"].values():
        assert gate["verdict"] in ("PASS", "FAIL") and gate["figures"]["simulated"]["frames"] == 6 - 3
    assert all(row["p50_ms"] > 0 for row in figures["rows"])


@pytest.mark.parametrize("argv,message", [(["--configs", "huge"], "huge"),
                                          (["--http-runtimes", "openvino"], "runtime/precision")])
def test_bench_refuses_bad_arguments(capsys: pytest.CaptureFixture[str], argv, message):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_interleaved_timing_is_not_charged_for_the_path_before():
    """A run can leave work behind it (onnxruntime's pool threads spin on the cores after a run returns): the path
    timed next must not pay for it. Here every call pays 20 ms when another path ran just before it, 0 otherwise."""
    last = {"name": None}

    def path(name: str):
        def call(_: int) -> None:
            if last["name"] not in (None, name):
                time.sleep(0.02)  # the previous path's leftover work
            last["name"] = name
        return call

    samples = time_interleaved({"a": path("a"), "b": path("b")}, repeats=3)
    assert set(samples) == {"a", "b"} and all(len(s) == 3 for s in samples.values())
    assert max(max(s) for s in samples.values()) < 0.01
