"""rafd-bench: speed and memory of the model and the service, side by side in one run on this machine.

For each config (the shipped default and the paper's): PyTorch eager on the full window, onnxruntime on
the full window, onnxruntime streaming per frame (the service's path); then `POST /detect` over HTTP on
loopback against a real `rafd-serve` process (1 and N concurrent streams), memory per stream and with
100 streams, and FLOPs per frame against a measured float32 matmul peak. Prints one table.
"""
from __future__ import annotations

import argparse
import base64
import json
import logging
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import numpy as np

from rafd.preprocess import to_model_input

log = logging.getLogger("rafd.bench")


@dataclass
class Row:
    config: str
    path: str
    p50_ms: float
    p95_ms: float
    fps: float
    note: str = ""


@dataclass
class Report:
    rows: list[Row] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)


def percentiles(samples_s: Sequence[float]) -> tuple[float, float]:
    """Seconds -> (median ms, p95 ms)."""
    ms = np.asarray(samples_s, dtype=np.float64) * 1000.0
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 95))


def time_calls(call: Callable[[int], Any], repeats: int, warmup: int = 2) -> list[float]:
    """Seconds per call of call(i), after `warmup` untimed calls."""
    for i in range(warmup):
        call(i)
    samples = []
    for i in range(repeats):
        start = time.perf_counter()
        call(i)
        samples.append(time.perf_counter() - start)
    return samples


def simulated_frames(size: int, count: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """`count` simulated scans of size x size (uint8) and their true world poses [count, 3]."""
    from rafd.sim.sensor import Difficulty
    from rafd.sim.sequence import run_simulation

    sequence = run_simulation(seed, count, "test", size, Difficulty(), name="bench")
    return list(sequence.images), np.asarray(sequence.poses, dtype=np.float64)


def matmul_peak_gflops(threads: int, n: int = 1024, repeats: int = 10) -> float:
    """Measured single-precision matmul throughput (GFLOP/s) with `threads` torch threads."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        a = torch.randn(n, n)
        b = torch.randn(n, n)
        samples = time_calls(lambda _: torch.mm(a, b), repeats)
    finally:
        torch.set_num_threads(previous)
    return 2.0 * n**3 / min(samples) / 1e9


def count_flops(module: Any, *inputs: Any) -> float:
    """FLOPs of one call (matmul/conv/attention counted by torch's FlopCounterMode; grid_sample etc. not)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        module(*inputs)
    return float(counter.get_total_flops())


# ----------------------------------------------------------------------------- model paths
def export_forms(checkpoint: Path, out_dir: Path) -> dict[str, Path]:
    """The window and the step (streaming) ONNX forms of a checkpoint, through rafd-export."""
    from export.cli import main as export_main

    forms = {}
    for form in ("window", "step"):
        path = out_dir / f"{checkpoint.stem}.{form}.onnx"
        start = time.perf_counter()
        if export_main([str(checkpoint), str(path), "--form", form, "--no-verify"]) != 0:
            raise RuntimeError(f"rafd-export failed for {checkpoint} ({form})")
        log.info("exported %s in %.1f s (%.2f MB)", path.name, time.perf_counter() - start, path.stat().st_size / 1e6)
        forms[form] = path
    return forms


def bench_model(name: str, checkpoint: Path, work: Path, threads: int, repeats: int, report: Report) -> dict[str, Any]:
    """PyTorch window, ORT window and ORT streaming times of one checkpoint -> rows + facts."""
    import onnxruntime as ort
    import torch

    from rafd.checkpoint import load_checkpoint
    from rafd.runtime import OnnxRunner

    torch.set_num_threads(threads)
    model, cfg, _ = load_checkpoint(checkpoint)
    size, frames_per_window = cfg.input_size, cfg.num_frames
    images, poses = simulated_frames(size, repeats + 8, seed=7)
    inputs = [to_model_input(im) for im in images]
    window = torch.from_numpy(np.stack(inputs[:frames_per_window]))[None, :, None]  # [1, T, 1, S, S]
    window_poses = torch.from_numpy(poses[:frames_per_window].astype(np.float32))[None]  # [1, T, 3]

    with torch.no_grad():
        eager = time_calls(lambda _: model(window, window_poses), repeats)
    report.rows.append(Row(name, "pytorch eager, full window", *percentiles(eager), 1.0 / np.median(eager)))

    forms = export_forms(checkpoint, work)
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(forms["window"]), options, providers=["CPUExecutionProvider"])
    feeds = {"frames": window.numpy(), "poses": window_poses.numpy()}
    names = {i.name for i in session.get_inputs()}
    if names != set(feeds):
        raise RuntimeError(f"window graph inputs {sorted(names)}, expected {sorted(feeds)}")
    ort_window = time_calls(lambda _: session.run(None, feeds), repeats)
    report.rows.append(Row(name, "onnxruntime, full window", *percentiles(ort_window), 1.0 / np.median(ort_window)))

    runner = OnnxRunner(forms["step"], threads=threads)
    state = runner.new_state()
    for i in range(frames_per_window):  # past the warm-up: every timed step is a steady-state frame
        _, state = runner.step(state, inputs[i], poses[i])
    states = [state]

    def one_step(i: int) -> None:
        _, new_state = runner.step(states[0], inputs[frames_per_window + i % 8], poses[frames_per_window + i % 8])
        states[0] = new_state

    stream = time_calls(one_step, repeats, warmup=0)
    p50, p95 = percentiles(stream)
    speedup = float(np.median(ort_window) / np.median(stream))
    report.rows.append(Row(name, "onnxruntime streaming step", p50, p95, 1.0 / np.median(stream),
                           f"{speedup:.2f}x faster than the ORT window"))

    step_flops = count_step_flops(model, cfg)
    window_flops = count_flops(model, window, window_poses)
    gflops = step_flops / np.median(stream) / 1e9
    report.facts[name] = {
        "input_size": size,
        "num_frames": frames_per_window,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        "onnx_step_mb": round(forms["step"].stat().st_size / 1e6, 2),
        "gflop_per_step": round(step_flops / 1e9, 3),
        "gflop_per_window": round(window_flops / 1e9, 3),
        "achieved_gflops_streaming": round(gflops, 1),
        "stream_state_bytes": int(state.nbytes),
        "streaming_speedup": round(speedup, 2),
    }
    return {"step_onnx": forms["step"], "cfg": cfg, "model_ms": p50}


def count_step_flops(model: Any, cfg: Any) -> float:
    """FLOPs of one streaming step: the exported StepGraph itself (new frame, newest pair flow, detect)."""
    from export.step import build_graph, example_inputs, feature_channels

    return count_flops(build_graph(model, cfg, "step"), *example_inputs(cfg, "step", feature_channels(model, cfg)))


# ----------------------------------------------------------------------------- HTTP path
def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(model: Path, threads: int, max_streams: int) -> tuple[subprocess.Popen, str]:
    """A real `rafd-serve` process on loopback; returns once /health/ready answers 200."""
    import httpx

    port = free_port()
    env = {**os.environ, "RAFD_MAX_STREAMS": str(max_streams), "RAFD_SCORE_THRESHOLD": "0.3"}
    command = [sys.executable, "-m", "service.cli", "--model", str(model), "--port", str(port),
               "--threads", str(threads), "--log-level", "warning"]
    process = subprocess.Popen(command, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"rafd-serve exited with {process.returncode}")
        try:
            if httpx.get(f"{url}/health/ready", timeout=1.0).status_code == 200:
                return process, url
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    process.kill()
    raise RuntimeError("rafd-serve did not become ready in 120 s")


def rss_bytes(pid: int) -> int:
    """Resident memory of a process (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def encode_png(image: np.ndarray) -> str:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return base64.b64encode(data.tobytes()).decode("ascii")


def load_streams(url: str, bodies: list[str], poses: np.ndarray, streams: int, frames: int) -> dict[str, Any]:
    """`streams` client threads, each posting `frames` frames of its own stream back to back."""
    import httpx

    latencies: list[float] = []
    timings: list[dict[str, float]] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(index: int) -> None:
        with httpx.Client(base_url=url, timeout=60.0) as http:
            for k in range(frames):
                j = k % len(bodies)
                body = {"stream_id": f"bench-{streams}-{index}", "timestamp": 1000.0 + k * 0.25,
                        "pose": {"x": float(poses[j, 0]), "y": float(poses[j, 1]), "yaw": float(poses[j, 2])},
                        "image": bodies[j]}
                start = time.perf_counter()
                answer = http.post("/detect", json=body)
                elapsed = time.perf_counter() - start
                with lock:
                    if answer.status_code != 200:
                        errors.append(answer.text[:200])
                    else:
                        latencies.append(elapsed)
                        timings.append(answer.json()["timing"])

    start = time.perf_counter()
    workers = [threading.Thread(target=client, args=(i,)) for i in range(streams)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    wall = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"{len(errors)} failed requests, first: {errors[0]}")
    return {"latencies": latencies, "timings": timings, "fps": len(latencies) / wall}


def bench_http(name: str, model: Path, size: int, threads: int, frames: int, concurrency: Sequence[int],
               report: Report) -> None:
    import httpx

    images, poses = simulated_frames(size, 16, seed=11)
    bodies = [encode_png(image) for image in images]
    process, url = start_server(model, threads, max_streams=1000)
    try:
        for streams in concurrency:
            result = load_streams(url, bodies, poses, streams, frames)
            p50, p95 = percentiles(result["latencies"])
            server = {k: statistics.median(t[k] for t in result["timings"])
                      for k in ("decode_ms", "model_ms", "post_ms", "total_ms", "wait_ms")}
            client_ms = p50
            overhead = (client_ms - server["model_ms"]) / server["model_ms"]
            note = (f"median decode {server['decode_ms']:.1f} ms, model {server['model_ms']:.1f} ms, "
                    f"post+JSON {server['post_ms']:.1f} ms, lock wait {server['wait_ms']:.1f} ms; "
                    f"HTTP+decode+JSON = {overhead * 100:.0f}% of model time")
            report.rows.append(Row(name, f"HTTP /detect, {streams} stream(s)", p50, p95, result["fps"], note))
        before = rss_bytes(process.pid)
        for index in range(100):  # 100 streams, each with a full buffer
            with httpx.Client(base_url=url, timeout=60.0) as http:
                for k in range(4):
                    body = {"stream_id": f"mem-{index}", "timestamp": float(k),
                            "pose": {"x": float(poses[k, 0]), "y": float(poses[k, 1]), "yaw": float(poses[k, 2])},
                            "image": bodies[k]}
                    if http.post("/detect", json=body, params={"flow": "false"}).status_code != 200:
                        raise RuntimeError("memory fill request failed")
        after = rss_bytes(process.pid)
        report.facts[name]["rss_before_100_streams_mb"] = round(before / 1e6, 1)
        report.facts[name]["rss_with_100_streams_mb"] = round(after / 1e6, 1)
        report.facts[name]["rss_per_stream_kb"] = round((after - before) / 100 / 1e3, 1)
    finally:
        process.terminate()
        process.wait(timeout=30)


# ----------------------------------------------------------------------------- table
def format_report(report: Report, machine: str) -> str:
    lines = [f"machine: {machine}", "",
             "| config | path | p50 ms | p95 ms | frames/s | note |", "|---|---|---|---|---|---|"]
    for row in report.rows:
        lines.append(f"| {row.config} | {row.path} | {row.p50_ms:.1f} | {row.p95_ms:.1f} | {row.fps:.1f} | {row.note} |")
    lines.append("")
    for name, facts in report.facts.items():
        lines.append(f"{name}: " + ", ".join(f"{k}={v}" for k, v in facts.items()))
    return "\n".join(lines)


def machine_description(threads: int) -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {len(os.sched_getaffinity(0))} usable cores, {threads} threads"


def paper_checkpoint(work: Path, input_size: int) -> Path:
    """The paper config with random weights (speed does not depend on the weights)."""
    import torch

    from rafd import RaFDConfig, build_model, save_checkpoint

    torch.manual_seed(0)
    cfg = RaFDConfig.paper().replace(input_size=input_size)
    path = work / "paper_random.pt"
    save_checkpoint(path, build_model(cfg).eval(), cfg, meta={"note": "random weights for timing"})
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, help="default: the shipped model (rafd.assets)")
    parser.add_argument("--configs", default="default,paper", help="comma list of default, paper")
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per model path")
    parser.add_argument("--http-frames", type=int, default=40, help="frames per stream in the HTTP load")
    parser.add_argument("--concurrency", default="1,8", help="comma list of concurrent streams")
    parser.add_argument("--no-http", action="store_true", help="model paths only")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would bury the table
    report = Report()
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    unknown = set(configs) - {"default", "paper"}
    if unknown:
        print(f"rafd-bench: error: unknown configs {sorted(unknown)}", file=sys.stderr)
        return 2
    concurrency = [int(c) for c in args.concurrency.split(",") if c.strip()]
    with tempfile.TemporaryDirectory(prefix="rafd-bench-") as tmp:
        work = Path(tmp)
        for name in configs:
            if name == "default":
                if args.checkpoint is not None:
                    checkpoint = args.checkpoint
                else:
                    from rafd.assets import default_checkpoint

                    checkpoint = default_checkpoint()
            else:
                checkpoint = paper_checkpoint(work, 256)
            if not Path(checkpoint).is_file():
                print(f"rafd-bench: error: checkpoint {checkpoint} not found", file=sys.stderr)
                return 2
            log.info("benchmarking %s (%s)", name, checkpoint)
            paths = bench_model(name, Path(checkpoint), work, args.threads, args.repeats, report)
            if not args.no_http:
                bench_http(name, paths["step_onnx"], paths["cfg"].input_size, args.threads, args.http_frames,
                           concurrency, report)
        report.facts["machine"] = {"matmul_peak_gflops": round(matmul_peak_gflops(args.threads), 1)}
    text = format_report(report, machine_description(args.threads))
    print(text)
    if args.json:
        args.json.write_text(json.dumps({"rows": [r.__dict__ for r in report.rows], "facts": report.facts}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
