"""rafd bench speed: speed, accuracy drift and memory of every runtime and precision, side by side in one run
(bench.speed; docs "Performance")."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from bench.flops import matmul_peaks_gflops
from bench.machine import machine_description
from bench.speed import (
    CONFIGS,
    MODEL_STAGES,
    Report,
    bench_http,
    bench_model,
    config_checkpoint,
    format_report,
    http_stages,
)
from rafd.cli import flags
from rafd.cpu import usable_cpus
from rafd.progress import Stages

log = logging.getLogger("bench")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("bench speed"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    flags.add_checkpoint(parser, nargs="?", what="the 'default' config's model (default: the shipped model)")
    parser.add_argument(
        "--configs",
        default="default,paper,paper-options",
        help=f"comma list of the configs to measure, of {', '.join(CONFIGS)} (default %(default)s)",
    )
    flags.add_threads(parser, usable_cpus(), "onnxruntime's / OpenVINO's threads per run (default: the CPUs)")
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per model path (default %(default)s)")
    parser.add_argument(
        "--concurrency-frames",
        type=int,
        default=8,
        metavar="N",
        help="frames per stream in the 1-vs-8-streams runner comparison (default %(default)s)",
    )
    parser.add_argument(
        "--gate-sequences", type=int, default=6, help="simulated sequences of the accuracy gate (default %(default)s)"
    )
    parser.add_argument(
        "--gate-sequence-frames",
        dest="gate_frames",
        type=int,
        default=40,
        metavar="N",
        help="frames per simulated sequence of the accuracy gate (default %(default)s)",
    )
    parser.add_argument("--no-gate", action="store_true", help="skip the accuracy gate")
    parser.add_argument(
        "--http-frames",
        type=int,
        default=40,
        metavar="N",
        help="frames per stream in the HTTP load (default %(default)s)",
    )
    parser.add_argument(
        "--concurrency", default="1,8", help="comma list of concurrent HTTP streams (default %(default)s)"
    )
    parser.add_argument(
        "--http-runtimes",
        default="onnxruntime/fp32,openvino/bf16",
        help="comma list of runtime/precision (or auto/auto) to serve over HTTP; unsupported ones are skipped",
    )
    parser.add_argument("--no-http", action="store_true", help="model paths only")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the figures as JSON")
    flags.add_quiet(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would bury the table
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    unknown = set(configs) - set(CONFIGS)
    if unknown:
        print(
            f"rafd bench speed: error: unknown configs {sorted(unknown)} (known: {', '.join(CONFIGS)})", file=sys.stderr
        )
        return 2
    from rafd.runtime import supported_choices

    supported = {f"{r}/{p}" for r, p in supported_choices()} | {"auto/auto"}
    http_runtimes = [c.strip() for c in args.http_runtimes.split(",") if c.strip()]
    bad = [c for c in http_runtimes if c.count("/") != 1]
    if bad:
        print(f"rafd bench speed: error: --http-runtimes takes runtime/precision pairs, got {bad}", file=sys.stderr)
        return 2
    skipped = [c for c in http_runtimes if c not in supported]
    if skipped:
        log.warning("not served over HTTP (this machine does not run them): %s", skipped)
    http_runtimes = [c for c in http_runtimes if c in supported]
    concurrency = [int(c) for c in args.concurrency.split(",") if c.strip()]
    report = Report()
    peaks = matmul_peaks_gflops(args.threads)
    report.facts["machine"] = {
        "matmul_peak_gflops": {k: round(v, 1) for k, v in peaks.items()},
        "runtimes": sorted(supported - {"auto/auto"}),
    }
    gate = None if args.no_gate else (args.gate_sequences, args.gate_frames)
    per_config = MODEL_STAGES + (0 if args.no_http else len(http_runtimes) * http_stages(concurrency, False))
    total = len(configs) * per_config + (0 if args.no_http or "default" not in configs else len(http_runtimes))
    stages = Stages("bench speed", total)
    with stages, tempfile.TemporaryDirectory(prefix="rafd-bench-") as tmp:
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
                print(f"rafd bench speed: error: checkpoint {checkpoint} not found", file=sys.stderr)
                return 2
            log.info("benchmarking %s (%s)", name, checkpoint)
            paths = bench_model(
                name,
                Path(checkpoint),
                work,
                args.threads,
                args.repeats,
                args.concurrency_frames,
                gate,
                peaks,
                report,
                stages,
            )
            if not args.no_http:
                for choice in http_runtimes:
                    runtime, precision = choice.split("/")
                    bench_http(
                        name,
                        paths["step_onnx"],
                        paths["cfg"].input_size,
                        args.threads,
                        args.http_frames,
                        concurrency,
                        runtime,
                        precision,
                        name == "default",
                        report,
                        stages,
                    )
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
