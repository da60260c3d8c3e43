"""rafd bench accuracy: the synthetic accuracy benchmark: simulate its data, train and score its variants, compare
two models (bench.accuracy)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from bench.accuracy import BENCHMARK_RECIPE, BenchmarkRun, compare_models, make_data, markdown_table, run_benchmark
from bench.variants import DEFAULT_VARIANTS, VARIANTS
from rafd.cli import flags


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=flags.prog("bench accuracy"), description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True, metavar="{data,run,compare}")
    data = commands.add_parser("data", help="simulate the fixed benchmark's train and test sequences")
    flags.add_out(data, "ROOT", "data root to write (train and test sequences)", required=True)
    data.add_argument("--scale", type=float, default=1.0, help="multiply sequence counts (smoke tests: < 1)")
    flags.add_sequence_frames(data, None, "default: the benchmark's; fewer for smoke tests")
    flags.add_quiet(data)
    run = commands.add_parser("run", help="train every variant with the same budget and seed, evaluate on test")
    run.add_argument(
        "data_root", type=Path, metavar="ROOT", help="the benchmark's data root (rafd bench accuracy data)"
    )
    flags.add_out(
        run, "DIR", "folder of the run: one sub-folder per variant (checkpoint, metrics, detections)", required=True
    )
    run.add_argument("--variants", default=",".join(DEFAULT_VARIANTS), help=f"comma list of {sorted(VARIANTS)}")
    run.add_argument("--epochs", type=int, help="epochs per variant (default: the recipe's)")
    run.add_argument("--batch-size", type=int, help="global batch (default: the recipe's)")
    run.add_argument("--lr", type=float, help="learning rate (default: the recipe's)")
    run.add_argument("--seed", type=int, default=0, help="seed of every variant's training (default 0)")
    flags.add_config(run, _recipes(), BENCHMARK_RECIPE, "the training recipe of every variant")
    run.add_argument("--full-scan", action="store_true", help="also score every variant on whole test scans")
    flags.add_device(run)
    run.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32", help="training autocast")
    run.add_argument("--max-windows", type=int, help="cap training windows (smoke tests)")
    run.add_argument("--max-steps-per-epoch", type=int, help="cap steps per epoch (smoke tests)")
    flags.add_resume(
        run,
        "each variant already in --out goes on from its last finished epoch instead of training again; a finished "
        "variant is only evaluated",
    )
    flags.add_quiet(run)
    compare = commands.add_parser(
        "compare", help="paired bootstrap over drives: is CANDIDATE better than BASELINE on the same frames?"
    )
    compare.add_argument(
        "baseline",
        type=Path,
        help="detections (.npz from rafd eval --detections, or a variant's "
        "folder of a run, which holds test_detections.npz)",
    )
    compare.add_argument("candidate", type=Path, help="the same for the other model")
    compare.add_argument("--resamples", type=int, default=2000, help="bootstrap resamples (default 2000)")
    compare.add_argument("--seed", type=int, default=0, help="bootstrap seed (default 0)")
    compare.add_argument("--json", type=Path, metavar="FILE", help="write the comparison here")
    flags.add_quiet(compare)
    return parser


def _recipes() -> list[str]:
    from rafd.train.recipes import RECIPES

    return list(RECIPES)


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from rafd.eval.run import EvalError
    from rafd.train.run import TrainSetupError

    try:
        if args.command == "data":
            print(make_data(args.out, args.scale, args.frames))
        elif args.command == "compare":
            print(compare_models(args.baseline, args.candidate, args.resamples, args.seed, args.json))
        else:
            variants = tuple(n.strip() for n in args.variants.split(",") if n.strip())
            rows = run_benchmark(
                BenchmarkRun(
                    args.data_root,
                    args.out,
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
        print(f"rafd bench accuracy: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
