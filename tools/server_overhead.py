"""The HTTP server layer's cost per request, side by side: uvicorn's httptools protocol (what rafd-serve ran before
issue 34), the service's httptools protocol with head limits (service/http/head_limits.py, what it runs now) and
uvicorn's h11 protocol (the pure-Python parser that bounds a head's size itself: the alternative considered).

    python -m tools.server_overhead [--requests 300] [--rounds 5]

Starts one server per variant on loopback, each in its own process, all serving the same app: the service with a
stub runner (no model time: what is left is the server, the middlewares, parsing and the answer). Then, in rounds
(the variants' order rotated each round, so a shared machine's drift falls on all of them), it sends --requests
requests of each kind to each variant over one keep-alive `http.client` connection: GET /health/live, and POST
/detect with a 128 px frame and a pose as JSON. Prints, per variant and kind, the median over rounds of each round's
median client latency, and of the server's CPU time per request (/proc: user + system). Loopback only, bounded.
Imports no torch.
"""

from __future__ import annotations

import argparse
import http.client
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from bench.server import cpu_seconds, free_port, wait_ready
from rafd import detect_client, progress
from rafd.cli import flags
from rafd.config import RaFDConfig
from rafd.cpu import usable_cpus
from rafd.runtime import StreamRunner

HOST = "127.0.0.1"
VARIANTS = {
    "httptools": "uvicorn's httptools protocol, no head limits (rafd-serve before issue 34)",
    "limited": "service.http.head_limits: httptools with the head limits (rafd-serve now)",
    "h11": "uvicorn's h11 protocol, h11_max_incomplete_event_size = the head limit",
}
KINDS = ("GET /health/live", "POST /detect")


# ------------------------------------------------------------------------------------------------ the server side
class StubBackend:
    """A step graph with no model behind it (single-frame, no cache): one box scoring 0 (under any threshold)."""

    runtime = "stub"
    precision = "fp32"
    threads = 1
    concurrent_runs = 1

    def __init__(self) -> None:
        config = RaFDConfig.tiny(num_frames=1)  # 128 px input
        self.metadata = {"config": config.to_json(), "version": "stub"}
        self.input_shapes = {"frame": (1, 1, config.input_size, config.input_size), "pose": (1, 3)}
        self.output_names: tuple[str, ...] = ("heatmap", "scores", "boxes", "frames_used")
        self._heatmap = np.zeros((1, 1, config.feature_size, config.feature_size), np.float32)

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {
            "heatmap": self._heatmap,
            "scores": np.zeros((1, 1), np.float32),
            "boxes": np.zeros((1, 1, 5), np.float32),
            "frames_used": np.ones(1, np.float32),
        }


def serve(variant: str, port: int) -> None:
    """Run one variant's server until terminated (the child process's entry point)."""
    import uvicorn

    from service.app import create_app
    from service.http.server import server_config
    from service.settings import Settings

    settings = Settings(threads=1, concurrent_runs=1, refusal_penalty_s=0.0)
    app = create_app(settings, runner=StreamRunner(StubBackend()))
    if variant == "limited":
        config = server_config(app, settings, HOST, port, log_level="warning")
    elif variant == "h11":
        limit = settings.max_request_line_bytes + settings.max_header_bytes
        config = uvicorn.Config(
            app, host=HOST, port=port, log_level="warning", http="h11", h11_max_incomplete_event_size=limit
        )
    else:
        config = uvicorn.Config(app, host=HOST, port=port, log_level="warning", http="httptools")
    uvicorn.Server(config).run()


# ------------------------------------------------------------------------------------------------ the client side
@dataclass
class Server:
    variant: str
    process: subprocess.Popen[bytes]
    port: int
    connection: http.client.HTTPConnection
    frames: int = 0
    latency_ms: dict[str, list[float]] = field(default_factory=lambda: {kind: [] for kind in KINDS})
    cpu_ms: dict[str, list[float]] = field(default_factory=lambda: {kind: [] for kind in KINDS})


def frame_request(server: Server) -> detect_client.DetectRequest:
    """The server's next frame: a 128 px scan with a moving spot and a pose, as JSON, without the flow."""
    server.frames += 1
    image = np.zeros((128, 128), np.uint8)
    image[32:40, 32 + server.frames % 64 : 40 + server.frames % 64] = 200
    fields = detect_client.FrameFields(
        float(server.frames), f"overhead-{server.variant}", (0.1 * server.frames, 0.0, 0.0)
    )
    return detect_client.detect_request(
        detect_client.json_body(fields, detect_client.base64_png(detect_client.png_bytes(image))), flow=False
    )


def request(server: Server, kind: str) -> None:
    if kind == "GET /health/live":
        server.connection.request("GET", "/health/live")
        response = server.connection.getresponse()
        response.read()
        status = response.status
    else:
        status, _ = detect_client.exchange(server.connection, frame_request(server))
    if status != 200:
        raise RuntimeError(f"{server.variant}: {kind} answered {status}")


def block(server: Server, kind: str, requests: int) -> None:
    """`requests` requests of one kind, timed; the server's CPU time over them."""
    server.connection.close()  # a new connection: the server closed the idle one after its keep-alive timeout
    for _ in range(10):  # the connection and the caches warm
        request(server, kind)
    latencies = []
    cpu = cpu_seconds(server.process.pid)
    for _ in range(requests):
        start = time.perf_counter()
        request(server, kind)
        latencies.append(time.perf_counter() - start)
    server.cpu_ms[kind].append(1000.0 * (cpu_seconds(server.process.pid) - cpu) / requests)
    server.latency_ms[kind].append(1000.0 * statistics.median(latencies))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.server_overhead", description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=300, help="timed requests per kind, variant and round")
    flags.add_count(parser, "--rounds", 5, 50, "rounds, the variants' order rotated each")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated, from " + ", ".join(VARIANTS))
    parser.add_argument("--serve", choices=sorted(VARIANTS), help=argparse.SUPPRESS)  # the child process
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    if args.serve:
        serve(args.serve, args.port)
        return 0
    variants = [v for v in args.variants.split(",") if v]
    if not variants or set(variants) - set(VARIANTS) or not 10 <= args.requests <= 5000:
        parser.error("bounded runs only: --requests 10-5000, variants from " + ", ".join(VARIANTS))

    servers: list[Server] = []
    try:
        for variant in variants:
            port = free_port()
            process = subprocess.Popen(
                [sys.executable, "-m", "tools.server_overhead", "--serve", variant, "--port", str(port)],
                env={k: v for k, v in os.environ.items() if not k.startswith("RAFD_")},
            )
            servers.append(Server(variant, process, port, detect_client.connect(f"http://{HOST}:{port}", timeout=30)))
            wait_ready(f"http://{HOST}:{port}", process, timeout=120.0)
        for round_ in progress.track(range(args.rounds), desc="server rounds", unit="round"):
            for server in servers[round_ % len(servers) :] + servers[: round_ % len(servers)]:
                for kind in KINDS:
                    block(server, kind, args.requests)
    finally:
        for server in servers:
            server.connection.close()
            server.process.terminate()
            server.process.wait(timeout=30)

    print(
        f"{args.rounds} rounds x {args.requests} requests per kind and variant, one keep-alive connection; "
        f"{usable_cpus()} usable CPUs; medians over rounds"
    )
    header = f"{'variant':<10} " + " ".join(f"{kind + ' ms':>22} {'server CPU ms':>13}" for kind in KINDS)
    print(header)
    for server in servers:
        cells = " ".join(
            f"{statistics.median(server.latency_ms[kind]):>22.3f} {statistics.median(server.cpu_ms[kind]):>13.3f}"
            for kind in KINDS
        )
        print(f"{server.variant:<10} {cells}")
    for variant in variants:
        print(f"  {variant}: {VARIANTS[variant]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
