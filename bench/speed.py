"""The speed benchmark (`rafd bench speed`): speed, accuracy drift and memory of every runtime and precision, side
by side in one run.

For each config (the shipped default model, the paper's network with random weights, and the paper's network with
the speed options flow.stride 8 and enhance.window 16):
  - PyTorch eager on the full window (the reference);
  - the streaming step (the service's path) on every runtime and precision this CPU runs (onnxruntime fp32,
    OpenVINO fp32, OpenVINO bf16 where the CPU has bf16), timed interleaved, with the achieved TFLOP/s against the
    fp32 and bf16 matmul peaks measured in the same run;
  - 1 stream against 8 concurrent streams through one runner, with one run at a time and with the service's
    default of one concurrent run per CPU;
  - the accuracy gate of every reduced precision against onnxruntime fp32 (export.gate_run, a small sample);
then `POST /detect` over HTTP on loopback against a real `rafd-serve` per runtime (1 and N streams, memory with
100 streams; for the default model also full 1152 px scans). Prints one table.
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.flops import count_flops
from bench.http_load import encode_png, load_streams
from bench.server import rss_bytes, start_server
from bench.timing import percentiles, time_calls, time_interleaved
from rafd.preprocess import model_crop, to_model_input
from rafd.progress import Stages

log = logging.getLogger("bench")

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


def simulated_frames(size: int, count: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """`count` simulated scans of size x size (uint8) and their true world poses [count, 3]."""
    from rafd.sim.sensor import Difficulty
    from rafd.sim.sequence import run_simulation

    sequence = run_simulation(seed, count, "test", size, Difficulty(), name="bench")
    return list(sequence.images), np.asarray(sequence.poses, dtype=np.float64)


def count_step_flops(model: Any, cfg: Any) -> float:
    """FLOPs of one streaming step: the exported StepGraph itself (new frame, newest pair flow, detect)."""
    from export.step import build_graph

    graph, example = build_graph(model, cfg)
    return count_flops(graph, *example)


# ----------------------------------------------------------------------------- model paths
def export_step(checkpoint: Path, out_dir: Path) -> Path:
    """The step graph of a checkpoint, through rafd-export (a batch of one: the benchmark steps one view)."""
    from export.cli import main as export_main

    path = out_dir / f"{checkpoint.stem}.step.onnx"
    start = time.perf_counter()
    if export_main([str(checkpoint), str(path), "--batch", "static", "--no-verify"]) != 0:
        raise RuntimeError(f"rafd-export failed for {checkpoint}")
    log.info("exported %s in %.1f s (%.2f MB)", path.name, time.perf_counter() - start, path.stat().st_size / 1e6)
    return path


def stream_fps(runner: Any, inputs: list[np.ndarray], poses: np.ndarray, streams: int, frames: int) -> float:
    """Aggregate frames/s of `streams` threads, each stepping its own stream `frames` times through `runner`."""

    def client(offset: int) -> None:
        state = runner.new_state()
        for k in range(frames):
            j = (offset + k) % len(inputs)
            _, state = runner.step(state, inputs[j][None], poses[j][None])

    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=streams) as pool:
        list(pool.map(client, range(streams)))  # list(): a client's exception surfaces here
    return streams * frames / (time.perf_counter() - start)


@dataclass
class ModelBench:
    """One checkpoint's benchmark, stage by stage (bench_model runs them in order); each stage adds rows to
    `report` and returns what a later stage or the facts need."""

    name: str
    model: Any  # the PyTorch RaFD
    cfg: Any  # its RaFDConfig
    threads: int
    repeats: int
    report: Report
    inputs: list[np.ndarray] = field(default_factory=list)  # model inputs [S, S] float32, window frames first
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # their true world poses [N, 3]

    def __post_init__(self) -> None:
        images, self.poses = simulated_frames(self.cfg.input_size, max(self.repeats, 8) + self.cfg.num_frames, seed=7)
        self.inputs = [to_model_input(im) for im in images]

    def window(self) -> tuple[Any, Any]:
        """The first window as the PyTorch forward takes it: frames [1, T, 1, S, S], poses [1, T, 3]."""
        import torch

        frames_per_window = self.cfg.num_frames
        frames = torch.from_numpy(np.stack(self.inputs[:frames_per_window]))[None, :, None]
        return frames, torch.from_numpy(self.poses[:frames_per_window].astype(np.float32))[None]

    def eager_window(self) -> None:
        import torch

        frames, poses = self.window()
        with torch.no_grad():
            eager = time_calls(lambda _: self.model(frames, poses), self.repeats)
        self.report.rows.append(
            Row(self.name, "pytorch eager, full window", *percentiles(eager), 1.0 / np.median(eager))
        )

    def streaming_steps(
        self, step_onnx: Path, choices: Sequence[tuple[str, str]], peaks: dict[str, float]
    ) -> tuple[dict[str, float], int]:
        """Every runtime's steady-state step, interleaved -> (achieved TFLOP/s per runtime, a stream state's bytes)."""
        from rafd.runtime import open_runner

        frames_per_window = self.cfg.num_frames
        step_flops = count_step_flops(self.model, self.cfg)
        from export.quantize import calibrate, quantize_model

        if ("openvino", "int8") in choices:  # int8 runs its own quantized graph, made as `rafd gate` makes it
            # within this stage (MODEL_STAGES counts the stages); a short calibration: the kernels' speed does not
            # depend on the activation ranges, only the accuracy does (which `rafd gate` judges on its own)
            quantize_model(step_onnx, calibration=calibrate(step_onnx, sequences=1, frames=8))
        runners = {f"{r}/{p}": open_runner(step_onnx, r, p, self.threads, islands=False) for r, p in choices}
        states = {}
        for key, runner in runners.items():  # past the warm-up: every timed step is a steady-state frame
            state = runner.new_state()
            for i in range(frames_per_window):
                _, state = runner.step(state, self.inputs[i][None], self.poses[i][None])
            states[key] = state

        def stepper(key: str) -> Callable[[int], None]:
            runner = runners[key]

            def one_step(i: int) -> None:
                j = frames_per_window + i % (len(self.inputs) - frames_per_window)
                _, states[key] = runner.step(states[key], self.inputs[j][None], self.poses[j][None])

            return one_step

        samples = time_interleaved({key: stepper(key) for key in runners}, self.repeats)
        reference = float(np.median(samples["onnxruntime/fp32"]))
        achieved = {}
        for key, seconds in samples.items():
            precision = key.split("/")[1]
            median = float(np.median(seconds))
            tflops = step_flops / median / 1e12
            achieved[key] = round(tflops, 3)
            note = f"{reference / median:.2f}x the ORT fp32 step; {tflops:.3f} TFLOP/s"
            if precision in peaks:
                note += f" = {100 * tflops * 1e3 / peaks[precision]:.0f}% of the {precision} matmul peak"
            self.report.rows.append(Row(self.name, f"streaming step, {key}", *percentiles(seconds), 1.0 / median, note))
        return achieved, int(states["onnxruntime/fp32"].nbytes)

    def concurrency(
        self, step_onnx: Path, choices: Sequence[tuple[str, str]], frames: int
    ) -> dict[str, dict[str, float]]:
        """1 against 8 streams through one runner, per runtime and per number of concurrent runs."""
        from rafd.runtime import open_runner

        found = {}
        for runtime, precision in choices:
            key = f"{runtime}/{precision}"
            for runs in sorted({1, self.threads}):
                runner = open_runner(step_onnx, runtime, precision, self.threads, concurrent_runs=runs)
                stream_fps(runner, self.inputs, self.poses, 1, self.cfg.num_frames)  # warm both compilations up
                stream_fps(runner, self.inputs, self.poses, 2, self.cfg.num_frames)
                one = stream_fps(runner, self.inputs, self.poses, 1, frames)
                eight = stream_fps(runner, self.inputs, self.poses, 8, frames)
                found[f"{key}, {runs} concurrent run(s)"] = {
                    "1_stream_fps": round(one, 1),
                    "8_streams_fps": round(eight, 1),
                    "ratio": round(eight / one, 2),
                }
                self.report.rows.append(
                    Row(
                        self.name,
                        f"8 streams through one runner, {key}, {self.threads} threads, {runs} concurrent run(s)",
                        1e3 * 8 / eight,
                        None,
                        eight,
                        f"{eight / one:.2f}x one stream's {one:.1f} frames/s (p50 column: mean ms per frame of a "
                        "stream)",
                    )
                )
        return found

    def gates(self, step_onnx: Path, choices: Sequence[tuple[str, str]], gate: tuple[int, int]) -> dict[str, Any]:
        """The accuracy gate of every reduced precision (export.gate_run) on `gate` = (sequences, frames)."""
        from export.gate_run import gate_model

        sample = os.environ.get("RAFD_RADIATE_SAMPLE")
        radiate = sample if sample and Path(sample, "Navtech_Cartesian").is_dir() else None
        found = {}
        for runtime, precision in choices:
            if precision == "fp32":
                continue
            result = gate_model(
                step_onnx,
                (runtime, precision),
                sequences=gate[0],
                frames=gate[1],
                radiate=radiate,
                threads=self.threads,
            )
            for line in result.lines():
                log.info("%s", line)
            found[f"{runtime}/{precision}"] = {
                "verdict": "PASS" if result.ok else "FAIL",
                "failed": [f"{s}: {c}" for s, c, _, _, ok in result.checks() if not ok],
                "figures": result.figures(),
            }
        return found


def bench_model(
    name: str,
    checkpoint: Path,
    work: Path,
    threads: int,
    repeats: int,
    concurrency_frames: int,
    gate: tuple[int, int] | None,
    peaks: dict[str, float],
    report: Report,
    stages: Stages | None = None,
) -> dict[str, Any]:
    """PyTorch window, the streaming step on every runtime, concurrency and the gate -> rows + facts
    (MODEL_STAGES stages, the gate's included, on `stages`)."""
    begin = stages.begin if stages is not None else (lambda _: None)
    import torch

    from rafd.model.checkpoint import load_checkpoint
    from rafd.runtime import supported_choices

    torch.set_num_threads(threads)
    model, cfg, _ = load_checkpoint(checkpoint)
    bench = ModelBench(name, model, cfg, threads, repeats, report)
    choices = supported_choices()

    begin(f"{name}: PyTorch eager window x {repeats}")
    bench.eager_window()
    begin(f"{name}: export the step graph")
    step_onnx = export_step(checkpoint, work)
    begin(f"{name}: streaming steps on every runtime, interleaved, x {repeats}")
    achieved, state_bytes = bench.streaming_steps(step_onnx, choices, peaks)
    begin(f"{name}: 1 against 8 streams through one runner")
    concurrency = bench.concurrency(step_onnx, choices, concurrency_frames)
    begin(f"{name}: accuracy gate" + ("" if gate is not None else " (skipped)"))
    gates = bench.gates(step_onnx, choices, gate) if gate is not None else {}

    report.facts[name] = {
        "input_size": cfg.input_size,
        "num_frames": cfg.num_frames,
        "config_options": {"flow.stride": cfg.flow.stride, "enhance_window_cells": cfg.enhance_window},
        "parameters": int(sum(p.numel() for p in model.parameters())),
        "onnx_step_mb": round(step_onnx.stat().st_size / 1e6, 2),
        "gflop_per_step": round(count_step_flops(model, cfg) / 1e9, 3),
        "gflop_per_window": round(count_flops(model, *bench.window()) / 1e9, 3),
        "achieved_tflops_streaming": achieved,
        "stream_state_bytes": state_bytes,
        "concurrency": concurrency,
        "gate": gates,
    }
    return {"step_onnx": step_onnx, "cfg": cfg}


MODEL_STAGES = 5  # the stages of bench_model


def http_stages(concurrency: Sequence[int], full_scans: bool) -> int:
    """The stages of bench_http: the server's start, each load, the memory fill."""
    return 1 + len(concurrency) + int(full_scans) + 1


def bench_http(
    name: str,
    model: Path,
    size: int,
    threads: int,
    frames: int,
    concurrency: Sequence[int],
    runtime: str,
    precision: str,
    full_scans: bool,
    report: Report,
    stages: Stages | None = None,
) -> None:
    import httpx

    begin = stages.begin if stages is not None else (lambda _: None)
    begin(f"{name}: start rafd serve ({runtime}/{precision})")
    images, poses = simulated_frames(max(FULL_SCAN, size) if full_scans else size, 16, seed=11)
    inputs = {"model-size": [encode_png(model_crop(image, size)) for image in images]}
    if full_scans:
        inputs[f"full {FULL_SCAN} px scans"] = [encode_png(image) for image in images]
    server = start_server(
        model,
        threads,
        env={
            "RAFD_MAX_STREAMS": "1000",
            "RAFD_RUNTIME": runtime,
            "RAFD_PRECISION": precision,
            "RAFD_SCORE_THRESHOLD": "0.3",
        },
    )
    url = server.url
    try:
        served = httpx.get(f"{url}/model", timeout=10.0).json()["runtime"]
        label = f"{served['runtime']}/{served['precision']}"
        for kind, bodies in inputs.items():
            for streams in concurrency if kind == "model-size" else [1]:
                begin(f"{name}: HTTP /detect, {label}, {kind}, {streams} stream(s) x {frames} frames")
                result = load_streams(url, bodies, poses, streams, frames, f"{label}-{kind}")
                p50, p95 = percentiles(result["latencies"])
                timing = {
                    k: statistics.median(a["timing"][k] for a in result["answers"])
                    for k in ("read_ms", "decode_ms", "model_ms", "post_ms", "total_ms", "wait_ms")
                }
                models = {(a["model"]["runtime"], a["model"]["precision"]) for a in result["answers"]}
                on_top = p50 - timing["model_ms"] - timing["decode_ms"]
                note = (
                    f"{kind}; median body read {timing['read_ms']:.1f} ms, PNG decode "
                    f"{timing['decode_ms']:.1f} ms, model {timing['model_ms']:.1f} ms, post "
                    f"{timing['post_ms']:.1f} ms; HTTP, decoding and JSON on top of model and PNG decode "
                    f"{on_top:.1f} ms (client p50)"
                )
                if models != {(served["runtime"], served["precision"])}:
                    raise RuntimeError(f"answers report runtimes {models}, /model says {label}")
                report.rows.append(
                    Row(name, f"HTTP /detect, {label}, {streams} stream(s)", p50, p95, result["fps"], note)
                )
        begin(f"{name}: memory with 100 streams ({label})")
        before = rss_bytes(server.pid)
        bodies = inputs["model-size"]
        with httpx.Client(base_url=url, timeout=120.0) as http:
            for index in range(100):  # 100 streams, each with a full buffer
                for k in range(4):
                    body = {
                        "stream_id": f"mem-{index}",
                        "timestamp": float(k),
                        "pose": {"x": float(poses[k, 0]), "y": float(poses[k, 1]), "yaw": float(poses[k, 2])},
                        "image": bodies[k],
                    }
                    if http.post("/detect", json=body, params={"flow": "false"}).status_code != 200:
                        raise RuntimeError("memory fill request failed")
        after = rss_bytes(server.pid)
        memory = report.facts[name].setdefault("rss_mb", {})
        memory[label] = {
            "before_100_streams": round(before / 1e6, 1),
            "with_100_streams": round(after / 1e6, 1),
            "per_stream_kb": round((after - before) / 100 / 1e3, 1),
        }
    finally:
        server.stop()


# ----------------------------------------------------------------------------- table
def format_report(report: Report, machine: str) -> str:
    lines = [
        f"machine: {machine}",
        "",
        "| config | path | p50 ms | p95 ms | frames/s | note |",
        "|---|---|---|---|---|---|",
    ]
    for row in report.rows:
        p95 = "-" if row.p95_ms is None else f"{row.p95_ms:.1f}"
        lines.append(f"| {row.config} | {row.path} | {row.p50_ms:.1f} | {p95} | {row.fps:.1f} | {row.note} |")
    lines.append("")
    for name, facts in report.facts.items():
        lines.append(f"{name}: " + json.dumps(facts, sort_keys=False))
    return "\n".join(lines)


def config_checkpoint(work: Path, name: str) -> Path:
    """The paper config (optionally with the speed options) with random weights (speed does not depend on them)."""
    import dataclasses

    import torch

    from rafd import RaFDConfig, build_model, save_checkpoint

    torch.manual_seed(0)
    cfg = RaFDConfig.paper()
    if name == "paper-options":
        cfg = cfg.replace(
            flow=dataclasses.replace(cfg.flow, stride=8), enhance=dataclasses.replace(cfg.enhance, window=16)
        )
    path = work / f"{name}_random.pt"
    save_checkpoint(path, build_model(cfg).eval(), cfg, meta={"note": "random weights for timing"})
    return path
