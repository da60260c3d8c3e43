"""rafd bench speed on the shipped model, model paths only (the service itself is exercised by the service tests):
every runtime and precision side by side, the matmul peaks, the concurrency comparison and the accuracy gate."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.machine import has_bf16_units
from bench.speed_cli import main
from rafd.runtime import supported_choices


@pytest.mark.slow
def test_bench_reports_every_runtime_side_by_side_and_writes_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.delenv("RAFD_RADIATE_SAMPLE", raising=False)  # simulated gate frames only: keeps the test short
    out = tmp_path / "bench.json"
    assert (
        main(
            [
                "--configs",
                "default",
                "--no-http",
                "--repeats",
                "2",
                "--threads",
                "1",
                "--concurrency-frames",
                "2",
                "--gate-sequences",
                "1",
                "--gate-sequence-frames",
                "6",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    table = capsys.readouterr().out
    choices = [f"{r}/{p}" for r, p in supported_choices()]
    for path in ["pytorch eager, full window"] + [f"streaming step, {c}" for c in choices]:
        assert f"| default | {path} |" in table
    figures = json.loads(out.read_text())
    facts, machine = figures["facts"]["default"], figures["facts"]["machine"]
    assert facts["num_frames"] == 4 and facts["gflop_per_window"] > facts["gflop_per_step"] > 0
    assert facts["stream_state_bytes"] > 0 and set(facts["achieved_tflops_streaming"]) == set(choices)
    assert machine["matmul_peak_gflops"]["fp32"] > 0
    # bf16 is timed only where the CPU computes it (emulated bf16 matmuls take minutes and no runtime uses them)
    assert ("bf16" in machine["matmul_peak_gflops"]) == has_bf16_units()
    assert set(facts["concurrency"]) == {f"{c}, 1 concurrent run(s)" for c in choices}  # 1 thread: one mode
    reduced = [c for c in choices if not c.endswith("fp32")]
    assert set(facts["gate"]) == set(reduced)
    for gate in facts["gate"].values():
        assert gate["verdict"] in ("PASS", "FAIL") and gate["figures"]["simulated"]["frames"] == 6 - 3
    assert all(row["p50_ms"] > 0 for row in figures["rows"])


@pytest.mark.parametrize(
    "argv,message", [(["--configs", "huge"], "huge"), (["--http-runtimes", "openvino"], "runtime/precision")]
)
def test_bench_refuses_bad_arguments(capsys: pytest.CaptureFixture[str], argv, message):
    assert main(argv) == 2
    assert message in capsys.readouterr().err
