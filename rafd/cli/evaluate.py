"""rafd-eval: mAP@0.3/0.5/0.7 and flow EPE of a checkpoint on a split, overall and per sequence, with plots."""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any, Sequence

log = logging.getLogger("rafd.eval")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-eval", description=__doc__)
    parser.add_argument("checkpoint", type=Path, help="checkpoint written by rafd-train")
    parser.add_argument("--data", required=True, type=Path, help="data root holding sequence folders")
    parser.add_argument("--split", required=True, action="append",
                        help="meta.json 'set'(s) to evaluate, e.g. test (repeat or comma-separate)")
    parser.add_argument("--cache", type=Path, help="scan cache written by rafd-prepare (default: decode the PNGs)")
    parser.add_argument("--estimate-poses", action="store_true",
                        help="run radar odometry for sequences without ego_poses.csv (slow; prefer rafd-odometry)")
    parser.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32", help="inference autocast")
    parser.add_argument("--full-scan", action="store_true",
                        help="score whole scans (tiles of the model's input, merged at their borders) on every "
                             "annotated vehicle instead of the protocol's centre crop")
    parser.add_argument("--score-threshold", type=float,
                        help="operating threshold for recall and false positives per frame (default: the "
                             "checkpoint's documented operating threshold, else 0.3)")
    parser.add_argument("--calibrate", type=float, metavar="FP_PER_FRAME",
                        help="choose the checkpoint's operating threshold on this data: the lowest score threshold "
                             "with at most FP_PER_FRAME false positives per frame (centre matching), written into "
                             "the checkpoint's meta (rafd-export carries it into the ONNX; the service uses it). "
                             "Use a validation split, never test data")
    parser.add_argument("--json", type=Path, help="write the metrics here")
    parser.add_argument("--detections", type=Path, metavar="NPZ",
                        help="write every frame's detections and ground truth here, for a paired comparison of two "
                             "models on the same frames (rafd-benchmark compare)")
    parser.add_argument("--plots", type=Path, help="folder for the precision-recall plot and example frames")
    parser.add_argument("--examples", type=int, default=4, help="example frames drawn into --plots")
    parser.add_argument("--mcap", type=Path, help="folder for Foxglove/MCAP logs, one <sequence>.mcap per sequence")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--device", default="auto", help="cpu | cuda | cuda:N | auto")
    parser.add_argument("--max-windows", type=int, help="evaluate at most N (evenly spaced) windows")
    parser.add_argument("--like-frames", type=int, metavar="N",
                        help="score only the frames an N-frame model scores (each sequence's first N-1 frames have "
                             "no full window): compares models of different frame counts on equal frames")
    parser.add_argument("--past-as-newest", action="store_true",
                        help="temporal ablation: replace every past frame of a window by the newest one (same pose), "
                             "so a multi-frame model sees only what a single-frame model sees; compare with the true "
                             "windows (rafd-benchmark compare on both --detections) to measure what the past adds")
    parser.add_argument("--threads", type=int, help="torch CPU threads")
    parser.add_argument("--no-progress", action="store_true")
    return parser


def _jsonable(value: Any) -> Any:
    """NaN and infinities -> None so the JSON is standard."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    return value


def calibrate(args: argparse.Namespace, results: list, cfg: Any, model: Any, meta: dict[str, Any]) -> float | None:
    """--calibrate: the lowest threshold within the false-positive budget -> written into the checkpoint's meta
    (atomically; weights and config untouched). None (and a message) when no threshold meets the budget."""
    from rafd.checkpoint import save_checkpoint
    from rafd.metrics import CENTRE_DISTANCE_M, match_centres

    centres = match_centres([r.predictions for r in results], [r.ground_truth for r in results], CENTRE_DISTANCE_M)
    recall, threshold = centres.recall_at_fp_rate(args.calibrate)
    if not math.isfinite(threshold):
        print(f"rafd-eval: error: no score threshold keeps within {args.calibrate} false positives per frame",
              file=sys.stderr)
        return None
    meta = dict(meta or {})
    meta["operating_threshold"] = threshold
    meta["operating_point"] = {"fp_per_frame_budget": args.calibrate, "recall": 100.0 * recall,
                               "data": str(args.data), "split": args.split, "full_scan": args.full_scan,
                               "frames": len(results)}
    save_checkpoint(args.checkpoint, model, cfg, meta)  # CPU copies of the weights, unchanged
    print(f"operating threshold {threshold:.4f} (recall {100 * recall:.1f}% with at most {args.calibrate:g} false "
          f"positives per frame on {args.split}) written into {args.checkpoint}")
    return threshold


TABLE_COLUMNS = ("mAP@0.3", "mAP@0.5", "mAP@0.7", "centre_AP", "recall_at_1fp", "recall_at_threshold",
                 "fp_per_frame_at_threshold", "epe_all", "frames")


def _rows(title: str, rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    lines = [f"{title:<28}" + "".join(f"{c[:14]:>15}" for c in TABLE_COLUMNS)]
    for name, row in rows:
        cells = []
        for column in TABLE_COLUMNS:
            value = row.get(column)
            cells.append(f"{value:>15.4f}" if isinstance(value, float) else f"{str(value):>15}")
        lines.append(f"{name:<28}" + "".join(cells))
    return lines


def format_table(overall: dict[str, Any], per_sequence: dict[str, dict[str, Any]],
                 per_condition: dict[str, dict[str, Any]] | None = None) -> str:
    """Plain-text table: one row per sequence plus the overall row; then, where the sequences' meta.json name
    their recording condition, one row per condition; then the figures by range."""
    lines = _rows("sequence", [*per_sequence.items(), ("OVERALL", overall)])
    if per_condition:
        lines += ["", *_rows("condition", list(per_condition.items()))]
    bands = [b for b in overall.get("by_range_at_threshold", []) if b["vehicles"] or b["fp_per_frame"]]
    if bands:
        lines.append(f"\nat the operating threshold {overall['score_threshold']:.4g}, by range from the radar:")
        lines.append(f"{'range (m)':<28}{'vehicles':>15}{'recall':>15}{'fp_per_frame':>15}")
        for band in bands:
            lines.append(f"{band['from_m']:>5.0f} - {band['to_m']:<20.0f}{band['vehicles']:>15}{band['recall']:>15.1f}"
                         f"{band['fp_per_frame']:>15.3f}")
    return "\n".join(lines)


EXAMPLE_SCORE = 0.3  # predictions drawn on example frames (the service's default threshold)


def write_plots(
    folder: Path, model: Any, cfg: Any, dataset: Any, results: Sequence[Any], examples: int, device: Any
) -> list[Path]:
    """Precision-recall plot of all frames and a few example frames (GT green, predictions red, flow)."""
    import cv2
    import numpy as np
    from torch.utils.data import Subset

    from rafd.metrics import precision_recall
    from rafd.train.predict import predict
    from rafd.viz import draw_detections, plot_precision_recall

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    pr_path = folder / "precision_recall.png"
    predictions, ground_truths = [r.predictions for r in results], [r.ground_truth for r in results]
    curves = {t: precision_recall(predictions, ground_truths, t) for t in (0.3, 0.5, 0.7)}
    plot_precision_recall(curves, pr_path)
    written.append(pr_path)
    if examples > 0 and len(dataset):
        # Frames that hold objects make better examples; fall back to any frame.
        with_objects = [i for i, r in enumerate(results) if len(r.ground_truth)] or list(range(len(results)))
        picks = sorted({with_objects[int(k)] for k in np.linspace(0, len(with_objects) - 1, min(examples, len(with_objects)))})
        example_results = predict(model, Subset(dataset, picks), cfg, device, batch_size=len(picks), keep_flow=True, progress=False)
        for index, result in zip(picks, example_results):
            window = dataset[index]
            image = np.asarray(window["frames"])[-1].squeeze()  # [H, W] newest frame
            shown = result.predictions[result.predictions[:, 5] >= EXAMPLE_SCORE]  # AP keeps all K; a picture cannot
            canvas = draw_detections(
                image,
                gt_boxes=result.ground_truth,
                pred_boxes=shown[:, :5],
                pred_scores=shown[:, 5],
                resolution=cfg.resolution,
                flow=result.flow,
                upscale=4,  # 128 px crops are too small to read the boxes at 1:1
            )
            path = folder / f"example_{result.sequence}_{result.frame:06d}.png"
            if not cv2.imwrite(str(path), canvas):
                raise OSError(f"could not write {path}")
            written.append(path)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    import torch

    from rafd.checkpoint import load_checkpoint
    from rafd.train.datasets import DatasetError, open_windows
    from rafd.train.distributed import resolve_device
    from rafd.train.predict import predict, summarise, summarise_by_condition, summarise_by_sequence

    if args.mcap is not None:
        try:
            from rafd.mcap_eval import write_evaluation_logs
        except ImportError as error:
            print(f"rafd-eval: error: --mcap needs the logs extra (pip install 'rafd[logs]'): {error}", file=sys.stderr)
            return 2
    if not args.checkpoint.is_file():
        print(f"rafd-eval: error: checkpoint {args.checkpoint} does not exist", file=sys.stderr)
        return 2
    if args.calibrate is not None and not (math.isfinite(args.calibrate) and args.calibrate > 0):
        print(f"rafd-eval: error: --calibrate needs a positive number of false positives per frame, got {args.calibrate}",
              file=sys.stderr)
        return 2
    if args.like_frames is not None and args.like_frames < 1:
        print(f"rafd-eval: error: --like-frames needs a number of frames >= 1, got {args.like_frames}", file=sys.stderr)
        return 2
    if args.past_as_newest and (args.full_scan or args.plots is not None or args.mcap is not None):
        print("rafd-eval: error: --past-as-newest scores the model's crop windows as numbers only; run it without "
              "--full-scan, --plots and --mcap", file=sys.stderr)
        return 2
    if args.full_scan and (args.plots is not None or args.mcap is not None):
        print("rafd-eval: error: --plots and --mcap draw the model's crop; run them without --full-scan", file=sys.stderr)
        return 2
    try:
        device = resolve_device(args.device)
        model, cfg, meta = load_checkpoint(args.checkpoint, map_location="cpu")
        data_cfg = cfg
        if args.full_scan:
            from rafd.train.fullscan import scan_config, scan_size_of

            data_cfg = scan_config(cfg, scan_size_of(args.data, args.split))
        dataset = open_windows(args.data, args.split, data_cfg, args.max_windows, augment=False, cache=args.cache,
                               estimate_poses=args.estimate_poses, history=args.like_frames)
    except (DatasetError, ValueError, RuntimeError) as error:
        print(f"rafd-eval: error: {error}", file=sys.stderr)
        return 2
    if args.threads:
        torch.set_num_threads(args.threads)
    model = model.to(device).eval()
    threshold = args.score_threshold if args.score_threshold is not None else float(
        (meta or {}).get("operating_threshold", 0.3))
    try:
        if args.full_scan:
            from rafd.train.fullscan import predict_full_scan

            results = predict_full_scan(model, dataset, cfg, device, precision=args.precision,
                                        progress=not args.no_progress)
        else:
            results = predict(model, dataset, cfg, device, batch_size=args.batch_size, progress=not args.no_progress,
                              precision=args.precision, keep_flow=args.mcap is not None,
                              past_as_newest=args.past_as_newest)
    except ValueError as error:
        print(f"rafd-eval: error: {error}", file=sys.stderr)
        return 2
    if args.calibrate is not None:
        threshold = calibrate(args, results, cfg, model, meta)
        if threshold is None:
            return 1
    overall = summarise(results, score_threshold=threshold)
    per_sequence = summarise_by_sequence(results, score_threshold=threshold)
    conditions = {sequence.name: sequence.condition for sequence in dataset.sequences}
    per_condition = summarise_by_condition(results, conditions, score_threshold=threshold)
    report = {
        "checkpoint": str(args.checkpoint),
        "data": str(args.data),
        "split": args.split,
        "num_frames": cfg.num_frames,
        "like_frames": args.like_frames,
        "input_size": cfg.input_size,
        "full_scan": args.full_scan,
        "past_as_newest": args.past_as_newest,
        "overall": overall,
        "per_sequence": per_sequence,
        "per_condition": per_condition,
        "checkpoint_meta": {k: meta.get(k) for k in ("epoch", "step") if isinstance(meta, dict)},
    }
    print(format_table(overall, per_sequence, per_condition))
    if args.plots is not None:
        paths = write_plots(args.plots, model, cfg, dataset, results, args.examples, device)
        report["plots"] = [str(p) for p in paths]
        print(f"plots: {args.plots} ({len(paths)} files)")
    if args.mcap is not None:
        paths = write_evaluation_logs(args.mcap, dataset, results, cfg, str(args.checkpoint))
        report["mcap"] = [str(p) for p in paths]
        print(f"MCAP logs: {args.mcap} ({len(paths)} files)")
    if args.detections is not None:
        from rafd.compare import save_detections

        save_detections(args.detections, results)
        report["detections"] = str(args.detections)
        print(f"detections: {args.detections}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(_jsonable(report), indent=2))
        print(f"metrics: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
