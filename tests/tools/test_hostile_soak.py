"""tools.hostile_soak and tools.server_overhead at a tiny scale: they serve, attack and report (their figures are
the scripts' job, measured in docs/performance.md; here only that they run, stay bounded, and that every attack is
refused as the service says it refuses it)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tools.hostile_soak import BODY_LIMIT, float_body, key_body

pytestmark = pytest.mark.network

REPO = Path(__file__).resolve().parents[2]


def test_the_json_floods_fit_the_body_limit_and_break_the_structure_bound():
    from service.body.requests import MAX_JSON_COMMAS, MAX_JSON_QUOTES
    from service.settings import Settings

    assert BODY_LIMIT == Settings().max_request_bytes
    for request in (float_body(), key_body()):
        head, _, body = request.partition(b"\r\n\r\n")
        assert f"Content-Length: {len(body)}".encode() in head and BODY_LIMIT - 8192 < len(body) <= BODY_LIMIT
        json.loads(body)  # valid JSON: the parser's problem, not a syntax error
        assert body.count(b",") > MAX_JSON_COMMAS
    assert key_body().count(b'"') > MAX_JSON_QUOTES


@pytest.mark.slow
def test_the_soak_runs_bounded_and_every_attack_is_refused(tmp_path):
    figures = tmp_path / "soak.json"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "tools.hostile_soak",
            "--minutes",
            "0.5",
            "--block-seconds",
            "6",
            "--streams",
            "1",
            "--attacks",
            "headers,slow-bodies,json-keys",
            "--json",
            str(figures),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={k: v for k, v in os.environ.items() if k != "RAFD_RADIATE_SAMPLE"},  # speckle stand-ins: quicker
    )
    assert out.returncode in (0, 1), out.stdout + out.stderr  # 1: a latency criterion missed at this tiny scale
    rows = json.loads(figures.read_text())["rows"]
    assert set(rows) == {"quiet", "headers", "slow-bodies", "json-keys"}
    assert set(rows["headers"]["attacker_codes"]) <= {"431"} and rows["headers"]["attacker_codes"]
    assert set(rows["slow-bodies"]["attacker_codes"]) <= {"408", "429"} and rows["slow-bodies"]["attacker_codes"]
    assert set(rows["json-keys"]["attacker_codes"]) == {"422"}
    assert all(set(row["normal_codes"]) <= {"200"} for row in rows.values())
    assert "server RSS:" in out.stdout and "normal requests served" in out.stdout


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


@pytest.mark.slow
def test_the_attacks_of_issue_40_are_refused(tmp_path):
    """The wide native scan is refused from its header (422), the degenerate one after decoding (422), and the slow
    bodies with made-up X-Forwarded-For addresses are one client's (408 / 429), while the normal stream is served."""
    figures = tmp_path / "soak.json"
    attacks = ("wide-native", "degenerate-native", "forwarded")
    out = subprocess.run(
        [sys.executable, "-m", "tools.hostile_soak", "--minutes", "0.5", "--block-seconds", "6", "--streams", "1"]
        + ["--attacks", ",".join(attacks), "--json", str(figures)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={k: v for k, v in os.environ.items() if k != "RAFD_RADIATE_SAMPLE"},
    )
    assert out.returncode in (0, 1), out.stdout + out.stderr  # 1: a latency criterion missed at this tiny scale
    rows = json.loads(figures.read_text())["rows"]
    assert set(rows) == {"quiet", *attacks}
    assert set(rows["wide-native"]["attacker_codes"]) == {"422"}
    assert set(rows["degenerate-native"]["attacker_codes"]) == {"422"}
    assert set(rows["forwarded"]["attacker_codes"]) <= {"408", "429"} and "429" in rows["forwarded"]["attacker_codes"]
    assert all(set(row["normal_codes"]) <= {"200"} for row in rows.values())
