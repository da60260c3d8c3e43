"""rafd bench capacity end to end on a short simulated drive: a real service on loopback, one level of crops, the
report naming what the service chose to serve (the figures are that path's)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.capacity_cli import main

pytest.importorskip("torch")  # the simulator


def test_capacity_reports_the_streams_held_and_the_path_that_served_them(tmp_path: Path, capsys):
    from rafd.sim.api import simulate_dataset

    simulate_dataset(tmp_path / "sim", 1, 6, 4242, split="test", size=1152)
    sample = next((tmp_path / "sim").iterdir())
    out = tmp_path / "capacity.json"
    argv = [str(sample), "--inputs", "crops", "--seconds", "1", "--max-streams", "1", "--budget-ms", "10000"]
    argv += ["--env", "RAFD_RUNTIME=onnxruntime", "--threads", "1", "--json", str(out), "--quiet"]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert report["served"]["default"]["runtime"] == "onnxruntime/fp32"
    (level,) = report["levels"].values()
    assert level["held"] == 1 and level["alone"]["statuses"] == {"200": level["alone"]["requests"]}
    assert "default: served as onnxruntime/fp32" in capsys.readouterr().out
