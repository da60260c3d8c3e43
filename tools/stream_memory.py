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
import time

from rafd import progress
from rafd.cli import flags


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.stream_memory", description=__doc__.splitlines()[0])
    flags.add_count(parser, "--streams", 200, 1000, "new streams per round")
    flags.add_count(parser, "--rounds", 2, 5, "rounds of streams that come and expire")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    _, args = flags.parse(build_parser, argv)
    import numpy as np
    from fastapi.testclient import TestClient

    from rafd import detect_client
    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner
    from service.app import create_app
    from service.settings import Settings

    runner = OnnxRunner(default_onnx(), threads=1)
    size = runner.config.input_size
    rng = np.random.default_rng(0)
    image = detect_client.base64_png(detect_client.png_bytes(rng.integers(0, 40, (size, size), dtype=np.uint8)))
    settings = Settings(threads=1, concurrent_runs=1, stream_ttl_s=300.0, max_streams=1000, refusal_penalty_s=0)
    now = [0.0]  # the store's clock: moved past the TTL to expire a round's streams at once
    with TestClient(create_app(settings, runner=runner, clock=lambda: now[0])) as client:
        deadline = time.monotonic() + 120.0  # the model loads in the lifespan's background task
        while client.get("/health/ready").status_code != 200:
            if time.monotonic() > deadline:
                raise SystemExit("the service was not ready within 120 s")
            time.sleep(0.05)
        start = rss_mb()
        print(f"after start-up: {start:.0f} MB RSS ({size} px frames, {args.streams} streams per round)")
        first_growth = 0.0
        for round_ in progress.track(range(args.rounds), desc="stream rounds", unit="round"):
            for k in range(args.streams):
                for t in range(2):
                    fields = detect_client.FrameFields(1.0 + 0.25 * t, f"r{round_}-s{k}", (0.0, 2.0 * t, 0.0))
                    body = fields.json_fields(image)
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
