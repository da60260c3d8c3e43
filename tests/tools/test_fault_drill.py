"""The fault drill (tools/fault_drill.py), bounded: the shipped nginx.conf on loopback in front of 3 rafd-serve
replicas, a replica killed with a frame in flight, the issue's returning stream with and without
`previous_timestamp`, and (to show the wrong-chain count can fail) the returning stream against replicas with the
staleness rule turned off, which continue the stale chain exactly as issue 39 found."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.loopback import LoopbackCluster, nginx_binary
from tools.fault_drill import PINNED, Drill, targets_missed

pytestmark = [pytest.mark.network, pytest.mark.slow]

if nginx_binary() is None:
    pytest.skip(
        "nginx is not installed (Debian: apt-get install nginx; .ci/run installs it where it may)",
        allow_module_level=True,
    )


def test_failover_loses_no_frame_and_gives_no_wrong_chain(tmp_path: Path):
    env = {**PINNED, "OMP_NUM_THREADS": "1"}
    with LoopbackCluster(3, tmp_path / "drill", env) as cluster:
        drill = Drill(cluster, streams=2, frames=12, retries=4)
        in_flight = drill.through_nginx("kill -9 in flight", drill.kill_in_flight, 4)
        returning = drill.returning(send_previous=True)
        old_client = drill.returning(send_previous=False)
        spaced = drill.keep_alive(posts=2, spacing=5.0)
    results = [in_flight, returning, old_client, spaced]
    assert targets_missed(results) == [], [r.line() for r in results]
    assert in_flight.frames == 24 and in_flight.lost == 0
    # the killed replica's frame came back as nginx's 502 in the service's JSON shape, then answered on a retry
    assert set(in_flight.error_codes) <= {"upstream_failed", "upstream_unavailable"}
    failed_attempts = sum(n for code, n in in_flight.codes.items() if code != 200) + in_flight.connection_errors
    assert in_flight.retries == failed_attempts  # every failed attempt was retried, and none was needed otherwise
    # the return to replica 0 restarted its chain, once, and said so
    assert returning.restarts == 1 and returning.wrong_chain == 0
    assert old_client.restarts == 1 and old_client.wrong_chain == 0  # 1.25 s apart: the gap rule alone
    assert spaced.codes == {200: 2}


def test_the_wrong_chain_count_sees_the_stale_return_when_the_rules_are_off(tmp_path: Path):
    env = {**PINNED, "OMP_NUM_THREADS": "1", "RAFD_STREAM_GAP_RESTART_S": "0"}
    with LoopbackCluster(2, tmp_path / "drill", env) as cluster:
        stale = Drill(cluster, streams=1, frames=4, retries=0).returning(send_previous=False)
    # frames 13-16 (k 12-15) back on replica 0 stacked on frames 6-8: frames_used 4, 4, 4, 4 where 1, 2, 3, 4 is true
    assert stale.wrong_chain == 3 and stale.restarts == 0
