"""tools.stream_memory at a tiny scale: it runs, stays bounded and prints what docs/deployment.md cites (its figures
are measured there, not here)."""

from __future__ import annotations

import pytest

from tools import stream_memory


@pytest.mark.slow
def test_stream_memory_runs_rounds_and_sees_the_streams_expire(capsys):
    assert stream_memory.main(["--streams", "2", "--rounds", "1"]) == 0
    out = capsys.readouterr().out
    assert "round 1: 2 streams" in out and "(0 left)" in out and "MB RSS per stream" in out
    with pytest.raises(SystemExit):
        stream_memory.main(["--streams", "0"])
