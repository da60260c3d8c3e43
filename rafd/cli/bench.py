"""rafd-bench: speed, accuracy drift and memory of every runtime and precision, side by side in one run.

For each config (the shipped default model, the paper's network with random weights, and the paper's network with
the speed options flow.stride 8 and enhance.window 16):
  - PyTorch eager and onnxruntime on the full window (the references);
  - the streaming step (the service's path) on every runtime and precision this CPU runs (onnxruntime fp32,
    OpenVINO fp32, OpenVINO bf16 where the CPU has bf16), timed interleaved, with the achieved TFLOP/s against the
    fp32 and bf16 matmul peaks measured in the same run;
  - 1 stream against 8 concurrent streams through one runner, with one run at a time and with the service's
    default of one concurrent run per CPU;
  - the accuracy gate of every reduced precision against onnxruntime fp32 (export.gate, a small sample);
then `POST /detect` over HTTP on loopback against a real `rafd-serve` per runtime (1 and N streams, memory with
100 streams; for the default model also full 1152 px scans). Prints one table.
"""
from __future__ import annotations

import argparse
import base64
import http.client
import json
import logging
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence
from urllib.parse import urlsplit

import cv2
import numpy as np

from rafd.preprocess import model_crop, to_model_input

log = logging.getLogger("rafd.bench")

CONFIGS = ("default", "paper", "paper-options")
FULL_SCAN = 1152  # a RADIATE Navtech Cartesian scan


@dataclass
class Row:
    config: str
    path: str
    p50_ms: float
    p95_ms: float | None  # None where only a mean is measured (aggregate throughput rows)
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


def time_interleaved(calls: dict[str, Callable[[int], Any]], repeats: int) -> dict[str, list[float]]:
    """Seconds per call of each call(i), one timed call of each per round: load from other jobs hits all alike.

    Each timed call follows one untimed call of the same path: a run leaves its runtime's pool threads busy after
    it returns (onnxruntime's threads spin on the cores for several milliseconds), which would slow whichever path came
    next (measured here: OpenVINO bf16 right after onnxruntime 34 ms, after its own untimed call 24 ms)."""
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for i in range(repeats):
        for name, call in calls.items():
            call(i)  # settles: the previous path's threads are idle again before the timed call
            start = time.perf_counter()
            call(i)
            samples[name].append(time.perf_counter() - start)
    return samples


def simulated_frames(size: int, count: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """`count` simulated scans of size x size (uint8) and their true world poses [count, 3]."""
    from rafd.sim.sensor import Difficulty
    from rafd.sim.sequence import run_simulation

    sequence = run_simulation(seed, count, "test", size, Difficulty(), name="bench")
    return list(sequence.images), np.asarray(sequence.poses, dtype=np.float64)


def matmul_peaks_gflops(threads: int, n: int = 2048, repeats: int = 5) -> dict[str, float]:
    """Measured n^3 matmul throughput (GFLOP/s, best of `repeats`) in float32 and bfloat16 with `threads` torch
    threads (oneDNN: AMX / avx512_bf16 where the CPU has them)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    peaks = {}
    try:
        for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
            a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
            samples = time_calls(lambda _: torch.mm(a, b), repeats)
            peaks[name] = 2.0 * n**3 / min(samples) / 1e9
    finally:
        torch.set_num_threads(previous)
    return peaks


def count_flops(module: Any, *inputs: Any) -> float:
    """FLOPs of one call (matmul/conv/attention counted by torch's FlopCounterMode; grid_sample etc. not)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        module(*inputs)
    return float(counter.get_total_flops())


def count_step_flops(model: Any, cfg: Any) -> float:
    """FLOPs of one streaming step: the exported StepGraph itself (new frame, newest pair flow, detect)."""
    from export.step import build_graph, example_inputs, feature_channels

    return count_flops(build_graph(model, cfg, "step"), *example_inputs(cfg, "step", feature_channels(model, cfg)))


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


def stream_fps(runner: Any, inputs: list[np.ndarray], poses: np.ndarray, streams: int, frames: int) -> float:
    """Aggregate frames/s of `streams` threads, each stepping its own stream `frames` times through `runner`."""
    def client(offset: int) -> None:
        state = runner.new_state()
        for k in range(frames):
            j = (offset + k) % len(inputs)
            _, state = runner.step(state, inputs[j], poses[j])

    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=streams) as pool:
        list(pool.map(client, range(streams)))  # list(): a client's exception surfaces here
    return streams * frames / (time.perf_counter() - start)


def bench_model(name: str, checkpoint: Path, work: Path, threads: int, repeats: int, concurrency_frames: int,
                gate: tuple[int, int] | None, peaks: dict[str, float], report: Report) -> dict[str, Any]:
    """PyTorch window, ORT window, the streaming step on every runtime, concurrency and the gate -> rows + facts."""
    import onnxruntime as ort
    import torch

    from rafd.checkpoint import load_checkpoint
    from rafd.runtime import open_runner, supported_choices

    torch.set_num_threads(threads)
    model, cfg, _ = load_checkpoint(checkpoint)
    size, frames_per_window = cfg.input_size, cfg.num_frames
    images, poses = simulated_frames(size, max(repeats, 8) + frames_per_window, seed=7)
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
    ort_window = time_calls(lambda _: session.run(None, feeds), repeats)
    report.rows.append(Row(name, "onnxruntime fp32, full window", *percentiles(ort_window), 1.0 / np.median(ort_window)))
    del session

    step_flops = count_step_flops(model, cfg)
    window_flops = count_flops(model, window, window_poses)
    choices = supported_choices()
    runners = {f"{r}/{p}": open_runner(forms["step"], r, p, threads) for r, p in choices}
    states = {}
    for key, runner in runners.items():  # past the warm-up: every timed step is a steady-state frame
        state = runner.new_state()
        for i in range(frames_per_window):
            _, state = runner.step(state, inputs[i], poses[i])
        states[key] = state

    def stepper(key: str) -> Callable[[int], None]:
        runner = runners[key]

        def one_step(i: int) -> None:
            j = frames_per_window + i % (len(inputs) - frames_per_window)
            _, states[key] = runner.step(states[key], inputs[j], poses[j])
        return one_step

    samples = time_interleaved({key: stepper(key) for key in runners}, repeats)
    reference = float(np.median(samples["onnxruntime/fp32"]))
    achieved = {}
    for key, seconds in samples.items():
        precision = key.split("/")[1]
        median = float(np.median(seconds))
        tflops = step_flops / median / 1e12
        achieved[key] = round(tflops, 3)
        note = (f"{reference / median:.2f}x the ORT fp32 step; {tflops:.3f} TFLOP/s = "
                f"{100 * tflops * 1e3 / peaks[precision]:.0f}% of the {precision} matmul peak")
        if key == "onnxruntime/fp32":
            note += f"; {float(np.median(ort_window)) / median:.2f}x faster than the ORT window"
        report.rows.append(Row(name, f"streaming step, {key}", *percentiles(seconds), 1.0 / median, note))

    concurrency = {}
    for key in runners:
        runtime, precision = key.split("/")
        for runs in sorted({1, threads}):
            runner = open_runner(forms["step"], runtime, precision, threads, concurrent_runs=runs)
            stream_fps(runner, inputs, poses, 1, frames_per_window)  # warm both compilations up
            stream_fps(runner, inputs, poses, 2, frames_per_window)
            one = stream_fps(runner, inputs, poses, 1, concurrency_frames)
            eight = stream_fps(runner, inputs, poses, 8, concurrency_frames)
            concurrency[f"{key}, {runs} concurrent run(s)"] = {"1_stream_fps": round(one, 1),
                                                                "8_streams_fps": round(eight, 1),
                                                                "ratio": round(eight / one, 2)}
            report.rows.append(Row(name, f"8 streams through one runner, {key}, {threads} threads, {runs} "
                                         f"concurrent run(s)", 1e3 * 8 / eight, None, eight,
                                   f"{eight / one:.2f}x one stream's {one:.1f} frames/s (p50 column: mean ms per "
                                   f"frame of a stream)"))

    gates = {}
    if gate is not None:
        from export.gate import gate_model

        sample = os.environ.get("RAFD_RADIATE_SAMPLE")
        radiate = sample if sample and Path(sample, "Navtech_Cartesian").is_dir() else None
        for runtime, precision in choices:
            if precision == "fp32":
                continue
            result = gate_model(forms["step"], (runtime, precision), sequences=gate[0], frames=gate[1],
                                radiate=radiate, threads=threads)
            for line in result.lines():
                log.info("%s", line)
            gates[f"{runtime}/{precision}"] = {"verdict": "PASS" if result.ok else "FAIL",
                                               "failed": [f"{s}: {c}" for s, c, _, _, ok in result.checks() if not ok],
                                               "figures": result.figures()}
    runner = runners["onnxruntime/fp32"]
    report.facts[name] = {
        "input_size": size,
        "num_frames": frames_per_window,
        "config_options": {"flow.stride": cfg.flow.stride, "enhance_window_cells": cfg.enhance_window},
        "parameters": int(sum(p.numel() for p in model.parameters())),
        "onnx_step_mb": round(forms["step"].stat().st_size / 1e6, 2),
        "gflop_per_step": round(step_flops / 1e9, 3),
        "gflop_per_window": round(window_flops / 1e9, 3),
        "achieved_tflops_streaming": achieved,
        "stream_state_bytes": int(states["onnxruntime/fp32"].nbytes),
        "concurrency": concurrency,
        "gate": gates,
    }
    del runner, runners
    return {"step_onnx": forms["step"], "cfg": cfg}


# ----------------------------------------------------------------------------- HTTP path
def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(model: Path, threads: int, max_streams: int, runtime: str, precision: str
                 ) -> tuple[subprocess.Popen, str]:
    """A real `rafd-serve` process on loopback; returns once /health/ready answers 200."""
    import httpx

    port = free_port()
    env = {**os.environ, "RAFD_MAX_STREAMS": str(max_streams), "RAFD_SCORE_THRESHOLD": "0.3",
           "RAFD_RUNTIME": runtime, "RAFD_PRECISION": precision}
    command = [sys.executable, "-m", "service.cli", "--model", str(model), "--port", str(port),
               "--threads", str(threads), "--log-level", "warning"]
    process = subprocess.Popen(command, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 300
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
    raise RuntimeError("rafd-serve did not become ready in 300 s")


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


def load_streams(url: str, bodies: list[str], poses: np.ndarray, streams: int, frames: int, tag: str
                 ) -> dict[str, Any]:
    """`streams` client threads, each posting `frames` frames of its own stream back to back.

    Each thread keeps one plain `http.client` connection alive and encodes its body before the clock starts: the
    latency is the service's, not a client library's (httpx adds about 1 ms per request here)."""
    address = urlsplit(url)
    latencies: list[float] = []
    answers: list[dict[str, Any]] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(index: int) -> None:
        connection = http.client.HTTPConnection(address.hostname, address.port, timeout=120.0)
        try:
            for k in range(frames):
                j = k % len(bodies)
                body = {"stream_id": re.sub(r"[^A-Za-z0-9._~:@+-]", "_", f"bench-{tag}-{streams}-{index}"),
                        "timestamp": 1000.0 + k * 0.25,
                        "pose": {"x": float(poses[j, 0]), "y": float(poses[j, 1]), "yaw": float(poses[j, 2])},
                        "image": bodies[j]}
                raw = json.dumps(body).encode()
                start = time.perf_counter()
                connection.request("POST", "/detect", raw, {"Content-Type": "application/json"})
                response = connection.getresponse()
                text = response.read()
                elapsed = time.perf_counter() - start
                with lock:
                    if response.status != 200:
                        errors.append(text[:200].decode(errors="replace"))
                    else:
                        latencies.append(elapsed)
                        answers.append(json.loads(text))
        finally:
            connection.close()

    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=streams) as pool:
        list(pool.map(client, range(streams)))
    wall = time.perf_counter() - start
    if errors:
        raise RuntimeError(f"{len(errors)} failed requests, first: {errors[0]}")
    return {"latencies": latencies, "answers": answers, "fps": len(latencies) / wall}


def bench_http(name: str, model: Path, size: int, threads: int, frames: int, concurrency: Sequence[int],
               runtime: str, precision: str, full_scans: bool, report: Report) -> None:
    import httpx

    images, poses = simulated_frames(max(FULL_SCAN, size) if full_scans else size, 16, seed=11)
    inputs = {"model-size": [encode_png(model_crop(image, size)) for image in images]}
    if full_scans:
        inputs[f"full {FULL_SCAN} px scans"] = [encode_png(image) for image in images]
    process, url = start_server(model, threads, max_streams=1000, runtime=runtime, precision=precision)
    try:
        served = httpx.get(f"{url}/model", timeout=10.0).json()["runtime"]
        label = f"{served['runtime']}/{served['precision']}"
        for kind, bodies in inputs.items():
            for streams in (concurrency if kind == "model-size" else [1]):
                result = load_streams(url, bodies, poses, streams, frames, f"{label}-{kind}")
                p50, p95 = percentiles(result["latencies"])
                timing = {k: statistics.median(a["timing"][k] for a in result["answers"])
                          for k in ("read_ms", "decode_ms", "model_ms", "post_ms", "total_ms", "wait_ms")}
                models = {(a["model"]["runtime"], a["model"]["precision"]) for a in result["answers"]}
                on_top = p50 - timing["model_ms"] - timing["decode_ms"]
                note = (f"{kind}; median body read {timing['read_ms']:.1f} ms, PNG decode "
                        f"{timing['decode_ms']:.1f} ms, model {timing['model_ms']:.1f} ms, post "
                        f"{timing['post_ms']:.1f} ms; HTTP, decoding and JSON on top of model and PNG decode "
                        f"{on_top:.1f} ms (client p50)")
                if models != {(served["runtime"], served["precision"])}:
                    raise RuntimeError(f"answers report runtimes {models}, /model says {label}")
                report.rows.append(Row(name, f"HTTP /detect, {label}, {streams} stream(s)", p50, p95, result["fps"],
                                       note))
        before = rss_bytes(process.pid)
        bodies = inputs["model-size"]
        with httpx.Client(base_url=url, timeout=120.0) as http:
            for index in range(100):  # 100 streams, each with a full buffer
                for k in range(4):
                    body = {"stream_id": f"mem-{index}", "timestamp": float(k),
                            "pose": {"x": float(poses[k, 0]), "y": float(poses[k, 1]), "yaw": float(poses[k, 2])},
                            "image": bodies[k]}
                    if http.post("/detect", json=body, params={"flow": "false"}).status_code != 200:
                        raise RuntimeError("memory fill request failed")
        after = rss_bytes(process.pid)
        memory = report.facts[name].setdefault("rss_mb", {})
        memory[label] = {"before_100_streams": round(before / 1e6, 1), "with_100_streams": round(after / 1e6, 1),
                         "per_stream_kb": round((after - before) / 100 / 1e3, 1)}
    finally:
        process.terminate()
        process.wait(timeout=30)


# ----------------------------------------------------------------------------- table
def format_report(report: Report, machine: str) -> str:
    lines = [f"machine: {machine}", "",
             "| config | path | p50 ms | p95 ms | frames/s | note |", "|---|---|---|---|---|---|"]
    for row in report.rows:
        p95 = "-" if row.p95_ms is None else f"{row.p95_ms:.1f}"
        lines.append(f"| {row.config} | {row.path} | {row.p50_ms:.1f} | {p95} | {row.fps:.1f} | {row.note} |")
    lines.append("")
    for name, facts in report.facts.items():
        lines.append(f"{name}: " + json.dumps(facts, sort_keys=False))
    return "\n".join(lines)


def machine_description(threads: int) -> str:
    cpu, flags = "unknown CPU", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and cpu == "unknown CPU":
                cpu = line.split(":", 1)[1].strip()
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    units = [f for f in ("avx512_bf16", "amx_bf16", "amx_int8", "avx512_vnni") if f in flags] or ["no bf16 units"]
    return f"{cpu} ({', '.join(units)}), {len(os.sched_getaffinity(0))} usable cores, {threads} threads"


def config_checkpoint(work: Path, name: str) -> Path:
    """The paper config (optionally with the speed options) with random weights (speed does not depend on them)."""
    import dataclasses

    import torch

    from rafd import RaFDConfig, build_model, save_checkpoint

    torch.manual_seed(0)
    cfg = RaFDConfig.paper()
    if name == "paper-options":
        cfg = cfg.replace(flow=dataclasses.replace(cfg.flow, stride=8), enhance=dataclasses.replace(cfg.enhance, window=16))
    path = work / f"{name}_random.pt"
    save_checkpoint(path, build_model(cfg).eval(), cfg, meta={"note": "random weights for timing"})
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, help="default: the shipped model (rafd.assets)")
    parser.add_argument("--configs", default="default,paper,paper-options",
                        help=f"comma list of {', '.join(CONFIGS)}")
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per model path")
    parser.add_argument("--concurrency-frames", type=int, default=8,
                        help="frames per stream in the 1-vs-8-streams runner comparison")
    parser.add_argument("--gate-sequences", type=int, default=6, help="simulated sequences of the accuracy gate")
    parser.add_argument("--gate-frames", type=int, default=40, help="frames per gate sequence")
    parser.add_argument("--no-gate", action="store_true", help="skip the accuracy gate")
    parser.add_argument("--http-frames", type=int, default=40, help="frames per stream in the HTTP load")
    parser.add_argument("--concurrency", default="1,8", help="comma list of concurrent HTTP streams")
    parser.add_argument("--http-runtimes", default="onnxruntime/fp32,openvino/bf16",
                        help="comma list of runtime/precision (or auto/auto) to serve over HTTP; unsupported ones "
                             "are skipped")
    parser.add_argument("--no-http", action="store_true", help="model paths only")
    parser.add_argument("--json", type=Path, help="also write the figures as JSON")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would bury the table
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    unknown = set(configs) - set(CONFIGS)
    if unknown:
        print(f"rafd-bench: error: unknown configs {sorted(unknown)} (known: {', '.join(CONFIGS)})", file=sys.stderr)
        return 2
    from rafd.runtime import supported_choices

    supported = {f"{r}/{p}" for r, p in supported_choices()} | {"auto/auto"}
    http_runtimes = [c.strip() for c in args.http_runtimes.split(",") if c.strip()]
    bad = [c for c in http_runtimes if c.count("/") != 1]
    if bad:
        print(f"rafd-bench: error: --http-runtimes takes runtime/precision pairs, got {bad}", file=sys.stderr)
        return 2
    skipped = [c for c in http_runtimes if c not in supported]
    if skipped:
        log.warning("not served over HTTP (this machine does not run them): %s", skipped)
    http_runtimes = [c for c in http_runtimes if c in supported]
    concurrency = [int(c) for c in args.concurrency.split(",") if c.strip()]
    report = Report()
    peaks = matmul_peaks_gflops(args.threads)
    report.facts["machine"] = {"matmul_peak_gflops": {k: round(v, 1) for k, v in peaks.items()},
                               "runtimes": sorted(supported - {"auto/auto"})}
    gate = None if args.no_gate else (args.gate_sequences, args.gate_frames)
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
                checkpoint = config_checkpoint(work, name)
            if not Path(checkpoint).is_file():
                print(f"rafd-bench: error: checkpoint {checkpoint} not found", file=sys.stderr)
                return 2
            log.info("benchmarking %s (%s)", name, checkpoint)
            paths = bench_model(name, Path(checkpoint), work, args.threads, args.repeats, args.concurrency_frames,
                                gate, peaks, report)
            if not args.no_http:
                for choice in http_runtimes:
                    runtime, precision = choice.split("/")
                    bench_http(name, paths["step_onnx"], paths["cfg"].input_size, args.threads, args.http_frames,
                               concurrency, runtime, precision, name == "default", report)
        # measured again at the end: the peaks of the same run, before and after (the machine may be shared)
        after = matmul_peaks_gflops(args.threads)
        report.facts["machine"]["matmul_peak_gflops_at_end"] = {k: round(v, 1) for k, v in after.items()}
    text = format_report(report, machine_description(args.threads))
    print(text)
    if args.json:
        args.json.write_text(json.dumps({"rows": [r.__dict__ for r in report.rows], "facts": report.facts}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
