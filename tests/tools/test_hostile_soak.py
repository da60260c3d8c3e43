"""tools.hostile_soak at a tiny scale: it serves, attacks and reports (its figures are the script's job, measured in
docs/performance.md; here only that it runs, stays bounded, and that every attack is refused as the service says it
refuses it)."""

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
    """One bounded soak with the attacks of issue 34 (endless headers, slow bodies, a JSON key flood) and of issue 40
    (a too-wide native scan, refused from its header; a degenerate one, after decoding; slow bodies behind made-up
    X-Forwarded-For addresses, one client's), each refused as the service says, while the normal stream is served."""
    figures = tmp_path / "soak.json"
    attacks = ("headers", "slow-bodies", "json-keys", "wide-native", "degenerate-native", "forwarded")
    out = subprocess.run(
        [sys.executable, "-m", "tools.hostile_soak", "--minutes", "0.5", "--block-seconds", "5", "--streams", "1"]
        + ["--attacks", ",".join(attacks), "--json", str(figures)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env={k: v for k, v in os.environ.items() if k != "RAFD_RADIATE_SAMPLE"},  # speckle stand-ins: quicker
    )
    assert out.returncode in (0, 1), out.stdout + out.stderr  # 1: a latency criterion missed at this tiny scale
    rows = json.loads(figures.read_text())["rows"]
    assert set(rows) == {"quiet", *attacks}
    assert set(rows["headers"]["attacker_codes"]) <= {"431"} and rows["headers"]["attacker_codes"]
    assert set(rows["slow-bodies"]["attacker_codes"]) <= {"408", "429"} and rows["slow-bodies"]["attacker_codes"]
    assert set(rows["json-keys"]["attacker_codes"]) == {"422"}
    assert set(rows["wide-native"]["attacker_codes"]) == {"422"}
    assert set(rows["degenerate-native"]["attacker_codes"]) == {"422"}
    assert set(rows["forwarded"]["attacker_codes"]) <= {"408", "429"} and "429" in rows["forwarded"]["attacker_codes"]
    assert all(set(row["normal_codes"]) <= {"200"} for row in rows.values())
    assert "server RSS:" in out.stdout and "normal requests served" in out.stdout
