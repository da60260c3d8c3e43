"""`rafd-bench-accuracy`: the synthetic accuracy benchmark: simulate its data, train and score its variants, compare
two models (rafd.bench.accuracy)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from rafd.bench.accuracy import BENCHMARK_RECIPE, BenchmarkRun, compare_models, make_data, markdown_table, run_benchmark
from rafd.bench.variants import DEFAULT_VARIANTS, VARIANTS
from rafd.cli.common import renamed


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-bench-accuracy", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    data = commands.add_parser("data", help="simulate the fixed benchmark's train and test sequences")
    data.add_argument("out_root", type=Path)
    data.add_argument("--scale", type=float, default=1.0, help="multiply sequence counts (smoke tests: < 1)")
    data.add_argument("--frames", type=int, help="override frames per sequence (smoke tests)")
    run = commands.add_parser("run", help="train every variant with the same budget and seed, evaluate on test")
    run.add_argument("data_root", type=Path)
    run.add_argument("out_dir", type=Path)
    run.add_argument("--variants", default=",".join(DEFAULT_VARIANTS), help=f"comma list of {sorted(VARIANTS)}")
    run.add_argument("--epochs", type=int, help="default: the recipe's")
    run.add_argument("--batch-size", type=int, help="default: the recipe's")
    run.add_argument("--lr", type=float, help="default: the recipe's")
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--config", default=BENCHMARK_RECIPE, help="training recipe (rafd.train.recipes)")
    run.add_argument("--full-scan", action="store_true", help="also score every variant on whole test scans")
    run.add_argument("--device", default="auto")
    run.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32", help="training autocast")
    run.add_argument("--max-windows", type=int, help="cap training windows (smoke tests)")
    run.add_argument("--max-steps-per-epoch", type=int, help="cap steps per epoch (smoke tests)")
    run.add_argument(
        "--resume",
        action="store_true",
        help="continue each variant already in OUT_DIR from its last finished epoch (rafd-train --resume) "
        "instead of training it again; a finished variant is only evaluated",
    )
    compare = commands.add_parser(
        "compare", help="paired bootstrap over drives: is CANDIDATE better than BASELINE on the same frames?"
    )
    compare.add_argument(
        "baseline",
        type=Path,
        help="detections (.npz from rafd-eval --detections, or a variant's "
        "folder of a run, which holds test_detections.npz)",
    )
    compare.add_argument("candidate", type=Path, help="the same for the other model")
    compare.add_argument("--resamples", type=int, default=2000)
    compare.add_argument("--seed", type=int, default=0)
    compare.add_argument("--json", type=Path, help="write the comparison here")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from rafd.eval.run import EvalError
    from rafd.train.run import TrainSetupError

    try:
        if args.command == "data":
            print(make_data(args.out_root, args.scale, args.frames))
        elif args.command == "compare":
            print(compare_models(args.baseline, args.candidate, args.resamples, args.seed, args.json))
        else:
            variants = tuple(n.strip() for n in args.variants.split(",") if n.strip())
            rows = run_benchmark(
                BenchmarkRun(
                    args.data_root,
                    args.out_dir,
                    variants,
                    args.epochs,
                    args.batch_size,
                    args.lr,
                    args.seed,
                    args.config,
                    args.full_scan,
                    args.device,
                    args.precision,
                    args.max_windows,
                    args.max_steps_per_epoch,
                    args.resume,
                )
            )
            print(markdown_table(rows))
    except (FileNotFoundError, ValueError, RuntimeError, TrainSetupError, EvalError) as error:
        print(f"rafd-bench-accuracy: error: {error}", file=sys.stderr)
        return 2
    return 0


legacy_main = renamed("rafd-benchmark", "rafd-bench-accuracy", main)


if __name__ == "__main__":
    sys.exit(main())
