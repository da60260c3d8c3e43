"""Model cost per frame against batch size, side by side: onnxruntime and OpenVINO fp32, 1 and 2 threads per run,
and two 1-thread runs at once (what the service does when two streams' steps overlap, RAFD_CONCURRENT_RUNS=2).

    rafd bench batch MODEL.onnx [--batches 1,2,4,8] [--rounds 3]

MODEL: a step graph exported with a batch axis (`rafd export CHECKPOINT OUT --batch dynamic`). Each (runtime,
threads, batch) is compiled once; rounds interleave them so a shared machine's drift falls on all; prints each
one's median ms per frame over the rounds (inputs random, of the graph's shapes). Decides RAFD_MAX_BATCH
(docs/performance.md, "Streams per replica").
"""

from __future__ import annotations

import argparse
import statistics
import threading
import time

import numpy as np

from rafd import progress
from rafd.cli import flags
from rafd.runtime.ort_backend import OrtBackend

RUNTIMES = ("onnxruntime", "openvino")


def open_backend(path: str, runtime: str, threads: int):
    if runtime == "onnxruntime":
        return OrtBackend(path, threads)
    from rafd.runtime.openvino_backend import OpenVinoBackend

    return OpenVinoBackend(path, "fp32", threads)


def feeds_of(backend, batch: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {name: rng.random((batch, *shape[1:]), dtype=np.float32) for name, shape in backend.input_shapes.items()}


def per_frame_ms(backends: list, feeds: list[dict[str, np.ndarray]], batch: int, repeats: int) -> float:
    """Wall time per frame of `repeats` runs on each backend, the backends running at once (one thread each)."""

    def work(backend, feed) -> None:
        for _ in range(repeats):
            backend.run(feed)

    start = time.perf_counter()
    workers = [threading.Thread(target=work, args=pair) for pair in zip(backends, feeds)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return 1000.0 * (time.perf_counter() - start) / (repeats * batch * len(backends))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=flags.prog("bench batch"), description=__doc__.splitlines()[0])
    parser.add_argument("model", help="a step graph with a batch axis (rafd export ... --batch dynamic)")
    parser.add_argument("--batches", default="1,2,4,8", help="comma-separated batch sizes, 1-64 (default %(default)s)")
    flags.add_count(parser, "--rounds", 3, 20, "interleaved rounds")
    parser.add_argument(
        "--runtimes",
        default=",".join(RUNTIMES),
        help="comma-separated, from " + ", ".join(RUNTIMES) + " (default: all)",
    )
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    batches = [int(b) for b in args.batches.split(",") if b]
    runtimes = [r for r in args.runtimes.split(",") if r]
    if not batches or min(batches) < 1 or max(batches) > 64 or set(runtimes) - set(RUNTIMES):
        parser.error("--batches from 1-64, --runtimes from " + ", ".join(RUNTIMES))
    rng = np.random.default_rng(0)
    rows = []  # (label, backends, feeds, batch)
    for runtime in runtimes:
        single, double = open_backend(args.model, runtime, 1), open_backend(args.model, runtime, 2)
        if single.input_shapes["frame"][0] != -1:
            parser.error(f"{args.model}: no batch axis (export it with --batch dynamic)")
        second = open_backend(args.model, runtime, 1)  # the service's second concurrent run has its own compilation
        for batch in batches:
            rows.append((f"{runtime}, 2 threads, batch {batch}", [double], batch))
            rows.append((f"{runtime}, 1 thread, batch {batch}", [single], batch))
            rows.append((f"{runtime}, two 1-thread runs at once, batch {batch}", [single, second], batch))
    inputs = {label: [feeds_of(b, batch, rng) for b in backends] for label, backends, batch in rows}
    for label, backends, batch in rows:  # warm-up
        per_frame_ms(backends, inputs[label], batch, 1)
    results: dict[str, list[float]] = {label: [] for label, _, _ in rows}
    for _ in progress.track(range(args.rounds), desc="batch rounds", unit="round"):
        for label, backends, batch in rows:
            results[label].append(per_frame_ms(backends, inputs[label], batch, max(2, 8 // batch)))
    print(f"{args.model}: ms per frame, median of {args.rounds} rounds")
    for label, values in results.items():
        print(f"{label:<48} {statistics.median(values):7.1f}   ({' '.join(f'{v:.1f}' for v in values)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
