"""tools.server_overhead at a tiny scale: every variant is served and timed (its figures are measured in
docs/performance.md, not here)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.network

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_the_server_overhead_comparison_runs_every_variant():
    out = subprocess.run(
        [sys.executable, "-m", "tools.server_overhead", "--requests", "10", "--rounds", "1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    rows = [
        line.split() for line in out.stdout.splitlines() if line.split()[:1] in (["httptools"], ["limited"], ["h11"])
    ]
    assert [row[0] for row in rows] == ["httptools", "limited", "h11"]
    # latency cells (1, 3) are positive; the server's CPU cells (2, 4) are counted in the kernel's 10 ms clock ticks,
    # so over 10 cheap requests they may read 0
    assert all(len(row) == 5 for row in rows)
    assert all(float(row[1]) > 0 and float(row[3]) > 0 for row in rows)
    assert all(float(row[2]) >= 0 and float(row[4]) >= 0 for row in rows)
