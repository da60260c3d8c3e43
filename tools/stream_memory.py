"""The service's resident memory as streams come and expire: held at its high-water mark after they expire, and reused
(not grown) by the next streams.

    python -m tools.stream_memory [--streams 200] [--rounds 2]

In one process, the app with the shipped model (onnxruntime fp32, 1 thread) is driven in-process (Starlette's test
client, no sockets): each round posts 2 frames (model-size crops with poses) to each of --streams new streams, reads
the RSS, lets them expire (the store's clock moved past RAFD_STREAM_TTL_S), checks they are gone, and reads the RSS
again. Printed: RSS after
start-up, after each round's streams and after their expiry, and the growth per stream of the first round. Bounded:
--streams 1-1000, --rounds 1-5.
"""

from __future__ import annotations

import argparse
import sys


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.stream_memory", description=__doc__.splitlines()[0])
    parser.add_argument("--streams", type=int, default=200, help="new streams per round (1-1000)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of streams that come and expire (1-5)")
    args = parser.parse_args(argv)
    if not (1 <= args.streams <= 1000 and 1 <= args.rounds <= 5):
        parser.error("--streams 1-1000, --rounds 1-5")
    import numpy as np
    from fastapi.testclient import TestClient

    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner
    from service.app import create_app
    from service.settings import Settings
    from tests.utils.service_testing import detect_json, wait_ready

    runner = OnnxRunner(default_onnx(), threads=1)
    size = runner.config.input_size
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 40, (size, size), dtype=np.uint8)
    settings = Settings(threads=1, concurrent_runs=1, stream_ttl_s=300.0, max_streams=1000, refusal_penalty_s=0)
    now = [0.0]  # the store's clock: moved past the TTL to expire a round's streams at once
    with TestClient(create_app(settings, runner=runner, clock=lambda: now[0])) as client:
        wait_ready(client, timeout=120.0)
        start = rss_mb()
        print(f"after start-up: {start:.0f} MB RSS ({size} px frames, {args.streams} streams per round)")
        first_growth = 0.0
        for round_ in range(args.rounds):
            for k in range(args.streams):
                for t in range(2):
                    body = detect_json(f"r{round_}-s{k}", 1.0 + 0.25 * t, frame, (0.0, 2.0 * t, 0.0))
                    response = client.post("/detect", json=body)
                    if response.status_code != 200:
                        raise SystemExit(f"frame refused: {response.text}")
            held = rss_mb()
            count = client.get("/streams").json()["count"]
            now[0] += 2 * settings.stream_ttl_s  # past the TTL
            after = client.get("/streams").json()["count"]  # expiry runs on store access
            expired = rss_mb()
            if round_ == 0:
                first_growth = (held - start) / args.streams
            print(
                f"round {round_ + 1}: {count} streams: {held:.0f} MB RSS; after they expired ({after} left): "
                f"{expired:.0f} MB"
            )
    print(f"first round: {first_growth:.2f} MB RSS per stream")
    return 0


if __name__ == "__main__":
    sys.exit(main())
