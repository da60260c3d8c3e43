"""tools.native_cost and tools.stream_memory at a tiny scale: they run, stay bounded and print what the docs cite
(their figures are measured in docs/api.md and docs/deployment.md, not here)."""

from __future__ import annotations

import pytest

from tools import native_cost, stream_memory


def test_native_cost_measures_every_case_including_the_largest_native_scan(capsys):
    assert native_cost.main(["--repeats", "1"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines()[1:]}
    assert set(rows) == set(native_cost.CASES)
    assert rows["native-max"][1] == "6859x400" and float(rows["native-max"][3]) == pytest.approx(2.74, abs=0.01)
    with pytest.raises(SystemExit):
        native_cost.main(["--repeats", "0"])


@pytest.mark.slow
def test_stream_memory_runs_rounds_and_sees_the_streams_expire(capsys):
    assert stream_memory.main(["--streams", "2", "--rounds", "1"]) == 0
    out = capsys.readouterr().out
    assert "round 1: 2 streams" in out and "(0 left)" in out and "MB RSS per stream" in out
    with pytest.raises(SystemExit):
        stream_memory.main(["--streams", "0"])
