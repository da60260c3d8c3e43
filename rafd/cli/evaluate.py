"""rafd eval: mAP@0.3/0.5/0.7 and flow EPE of a checkpoint on a split, overall and per sequence, with plots."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from rafd.cli import flags
from rafd.eval.run import EvalRun


def range_and_budget(text: str) -> tuple[float, float]:
    """ "50:2" -> (50.0, 2.0)."""
    try:
        from_m, budget = (float(part) for part in text.split(":"))
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected FROM_M:FP_PER_FRAME such as 50:2, got {text!r}") from error
    return from_m, budget


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=flags.prog("eval"), description=__doc__)
    flags.add_checkpoint(parser)
    parser.add_argument("data", type=Path, metavar="ROOT", help="data root holding sequence folders")
    flags.add_split(parser, "the splits to evaluate, e.g. test", required=True)
    parser.add_argument("--cache", type=Path, help="scan cache written by rafd prepare (default: decode the PNGs)")
    parser.add_argument(
        "--estimate-poses",
        action="store_true",
        help="run radar odometry for sequences without ego_poses.csv (slow; prefer rafd odometry)",
    )
    parser.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32", help="inference autocast")
    parser.add_argument(
        "--full-scan",
        action="store_true",
        help="score whole scans (tiles of the model's input, merged at their borders) on every "
        "annotated vehicle instead of the protocol's centre crop",
    )
    parser.add_argument(
        "--score-threshold",
        type=float,
        metavar="T",
        help="operating threshold for recall, false positives per frame and the boxes drawn in --plots (default: "
        "the checkpoint's operating threshold, else 0.3: what the service would answer)",
    )
    parser.add_argument(
        "--calibrate",
        type=float,
        metavar="FP_PER_FRAME",
        help="choose the checkpoint's operating threshold on this data: the lowest score threshold "
        "with at most FP_PER_FRAME false positives per frame (centre matching), written into "
        "the checkpoint's meta (rafd export carries it into the ONNX; the service uses it). "
        "Use a validation split, never test data",
    )
    parser.add_argument(
        "--calibrate-far",
        type=range_and_budget,
        metavar="FROM_M:FP_PER_FRAME",
        help="with --full-scan: choose a higher threshold for the detections FROM_M or more from the radar, the "
        "lowest at which the whole scans' false positives per frame have a 95%% upper bound (bootstrap over "
        "sequences) of at most FP_PER_FRAME, the near threshold kept (after --calibrate when given); written into "
        "the checkpoint's meta beside it. Use simulated validation drives where real labels do not reach",
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="write the metrics here")
    parser.add_argument(
        "--detections",
        type=Path,
        metavar="NPZ",
        help="write every frame's detections and ground truth here, for a paired comparison of two "
        "models on the same frames (rafd bench accuracy compare)",
    )
    parser.add_argument(
        "--plots",
        type=Path,
        metavar="DIR",
        help="folder for the precision-recall plot and example frames (boxes at or above the operating threshold)",
    )
    parser.add_argument("--examples", type=int, default=4, help="example frames drawn into --plots (default 4)")
    parser.add_argument(
        "--mcap-dir",
        dest="mcap",
        type=Path,
        metavar="DIR",
        help="folder for Foxglove/MCAP logs, one <sequence>.mcap each",
    )
    parser.add_argument("--batch-size", type=int, default=8, help="windows per forward (default 8)")
    flags.add_device(parser)
    parser.add_argument("--max-windows", type=int, help="evaluate at most N (evenly spaced) windows")
    flags.add_warm_up_windows(parser)
    parser.add_argument(
        "--like-frames",
        type=int,
        metavar="N",
        help="score only the frames an N-frame model scores (each sequence's first N-1 frames have "
        "no full window): compares models of different frame counts on equal frames",
    )
    parser.add_argument(
        "--past-as-newest",
        action="store_true",
        help="temporal ablation: replace every past frame of a window by the newest one (same pose), "
        "so a multi-frame model sees only what a single-frame model sees; compare with the true "
        "windows (rafd bench accuracy compare on both --detections) to measure what the past adds",
    )
    parser.add_argument(
        "--tracking",
        action="store_true",
        help="also track every sequence as a stream (rafd.tracking) and score it: HOTA/DetA/AssA, MOTA, IDF1 and ID "
        "switches (TrackEval, 2 m centre matching), velocity error of the four velocity candidates and two "
        "baselines, by range and weather, and the operating point with and without tracks (docs/tracking.md). "
        "Needs the metrics extra; use --warm-up-windows so every scan of a stream is answered",
    )
    flags.add_threads(parser, None, "torch's CPU threads (default: torch's)")
    flags.add_quiet(parser)
    return parser


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    return parser.parse_args(argv)


def eval_run(args: argparse.Namespace) -> EvalRun:
    """The flags as an EvalRun (one flag per field)."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(EvalRun) if f.name != "progress"}
    return EvalRun(**{**values, "split": flags.split_names(args.split), "progress": not args.quiet})


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from rafd.eval.run import CalibrationError, EvalError, evaluate
    from rafd.eval.table import format_flow_table, format_table

    try:
        report = evaluate(eval_run(args))
    except CalibrationError as error:
        print(f"rafd-eval: error: {error}", file=sys.stderr)
        return 1
    except EvalError as error:
        print(f"rafd-eval: error: {error}", file=sys.stderr)
        return 2
    for key in ("calibration", "calibration_far"):
        if key in report:
            print(report[key])
    print(format_table(report["overall"], report["per_sequence"], report["per_condition"]))
    print(format_flow_table(report["flow"]))
    if "tracking" in report:
        from rafd.eval.tracking_table import format_tracking

        print(format_tracking(report["tracking"]))
    for key, what in (("plots", "plots"), ("mcap", "MCAP logs")):
        if key in report:
            print(f"{what}: {getattr(args, key)} ({len(report[key])} files)")
    for key, what in (("detections", "detections"), ("json", "metrics")):
        if key in report:
            print(f"{what}: {report[key]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
