"""tools.decode_memory at a tiny scale: it runs, stays bounded and prints what the docs cite (its figures are measured
in docs/api.md, not here)."""

from __future__ import annotations

import pytest

from tools import decode_memory


def test_decode_memory_measures_every_case_including_the_largest_native_scan(capsys):
    assert decode_memory.main(["--repeats", "1"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines()[1:]}
    assert set(rows) == set(decode_memory.CASES)
    assert rows["native-max"][1] == "6859x400" and float(rows["native-max"][3]) == pytest.approx(2.74, abs=0.01)
    with pytest.raises(SystemExit):
        decode_memory.main(["--repeats", "0"])
