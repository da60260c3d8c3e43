"""rafd-bench on the shipped model, model paths only (the HTTP path is exercised by the service tests)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from rafd.cli.bench import main


def test_bench_prints_the_three_model_paths_and_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    out = tmp_path / "bench.json"
    assert main(["--configs", "default", "--no-http", "--repeats", "2", "--threads", "1", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    for path in ("pytorch eager, full window", "onnxruntime, full window", "onnxruntime streaming step"):
        assert f"| default | {path} |" in table
    figures = json.loads(out.read_text())
    facts = figures["facts"]["default"]
    assert facts["num_frames"] == 4 and facts["gflop_per_window"] > facts["gflop_per_step"] > 0
    assert facts["stream_state_bytes"] > 0 and figures["facts"]["machine"]["matmul_peak_gflops"] > 0
    assert all(row["p50_ms"] > 0 for row in figures["rows"])


def test_bench_refuses_unknown_configs(capsys: pytest.CaptureFixture[str]):
    assert main(["--configs", "huge"]) == 2
    assert "huge" in capsys.readouterr().err
