"""One evaluation as plain Python: `evaluate(EvalRun(...))` -> the report `rafd-eval` prints and writes. `rafd-eval`
builds an EvalRun from its flags (one flag per field); the synthetic benchmark builds its own (bench.accuracy).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rafd.protocol import IOU_THRESHOLDS, OperatingThreshold, operating_threshold

log = logging.getLogger("rafd.eval")


@dataclass(frozen=True)
class EvalRun:
    checkpoint: Path  # written by rafd-train
    data: Path  # data root holding sequence folders
    split: tuple[str, ...]  # meta.json splits to evaluate
    cache: Path | None = None  # scan cache written by rafd-prepare
    estimate_poses: bool = False
    precision: str = "fp32"  # inference autocast
    full_scan: bool = False  # whole scans by tiles instead of the protocol's centre crop
    score_threshold: float | None = None  # None: the checkpoint's operating threshold (rafd.protocol)
    calibrate: float | None = None  # choose and write the operating threshold at this many FP per frame
    calibrate_far: tuple[float, float] | None = None  # (from_m, FP per frame): choose and write the far threshold
    json: Path | None = None
    detections: Path | None = None  # every frame's detections and GT, for rafd bench accuracy compare
    plots: Path | None = None
    examples: int = 4
    mcap: Path | None = None
    batch_size: int = 8
    device: str = "auto"
    max_windows: int | None = None
    like_frames: int | None = None
    past_as_newest: bool = False
    warm_up_windows: bool = False  # also each sequence's first frames, in padded windows (as the service answers)
    tracking: bool = False  # also run the tracker over each sequence and score tracks and velocities
    threads: int | None = None
    progress: bool = True


class EvalError(Exception):
    """The evaluation cannot run as asked; the message says why (raised before or instead of any figure)."""


def check_run(run: EvalRun) -> None:
    """Refuse contradictory or impossible options before anything is loaded."""
    if not Path(run.checkpoint).is_file():
        raise EvalError(f"checkpoint {run.checkpoint} does not exist")
    if run.calibrate is not None and not (math.isfinite(run.calibrate) and run.calibrate > 0):
        raise EvalError(f"--calibrate needs a positive number of false positives per frame, got {run.calibrate}")
    if run.calibrate_far is not None:
        from_m, budget = run.calibrate_far
        if not run.full_scan:
            raise EvalError("--calibrate-far chooses a threshold for far detections: run it with --full-scan")
        if run.score_threshold is not None:
            raise EvalError("--calibrate-far keeps the checkpoint's near threshold: run it without --score-threshold")
        if not (math.isfinite(from_m) and from_m > 0 and math.isfinite(budget) and budget > 0):
            raise EvalError(f"--calibrate-far needs a positive range and false-positive budget, got {from_m}:{budget}")
    if run.like_frames is not None and run.like_frames < 1:
        raise EvalError(f"--like-frames needs a number of frames >= 1, got {run.like_frames}")
    if run.past_as_newest and (run.full_scan or run.plots is not None or run.mcap is not None):
        raise EvalError(
            "--past-as-newest scores the model's crop windows as numbers only; run it without "
            "--full-scan, --plots and --mcap"
        )
    if run.tracking and run.past_as_newest:
        raise EvalError("--tracking follows the real windows; run it without --past-as-newest")
    if run.full_scan and (run.plots is not None or run.mcap is not None):
        raise EvalError("--plots and --mcap draw the model's crop; run them without --full-scan")


def jsonable(value: Any) -> Any:
    """NaN and infinities -> None so the JSON is standard."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [jsonable(v) for v in value]
    return value


class CalibrationError(EvalError):
    """--calibrate found no score threshold within the false-positive budget (the figures were computed)."""


def calibrate(
    run: EvalRun, results: list[Any], cfg: Any, model: Any, meta: dict[str, Any]
) -> tuple[OperatingThreshold, str]:
    """--calibrate: the lowest threshold within the false-positive budget -> written into the checkpoint's meta
    (atomically; weights and config untouched). -> (threshold, a line saying so); CalibrationError when no threshold
    meets the budget."""
    from rafd.eval.metrics import match_centres
    from rafd.model.checkpoint import save_checkpoint
    from rafd.protocol import CENTRE_DISTANCE_M, OPERATING_THRESHOLD_KEY

    assert run.calibrate is not None
    centres = match_centres([r.predictions for r in results], [r.ground_truth for r in results], CENTRE_DISTANCE_M)
    recall, threshold = centres.recall_at_fp_rate(run.calibrate)
    if not math.isfinite(threshold):
        raise CalibrationError(f"no score threshold keeps within {run.calibrate} false positives per frame")
    meta = dict(meta or {})
    meta[OPERATING_THRESHOLD_KEY] = threshold
    meta["operating_point"] = {
        "fp_per_frame_budget": run.calibrate,
        "recall": 100.0 * recall,
        "data": str(run.data),
        "split": list(run.split),
        "full_scan": run.full_scan,
        "frames": len(results),
    }
    save_checkpoint(run.checkpoint, model, cfg, meta)  # CPU copies of the weights, unchanged
    return operating_threshold(meta), (
        f"operating threshold {threshold:.4f} (recall {100 * recall:.1f}% with at most "
        f"{run.calibrate:g} false positives per frame on {list(run.split)}) written into "
        f"{run.checkpoint}"
    )


def calibrate_far(run: EvalRun, results: list[Any], cfg: Any, model: Any) -> tuple[OperatingThreshold, str]:
    """--calibrate-far FROM_M:FP: the lowest threshold for detections FROM_M or more from the radar at which the whole
    scans' false positives per frame stay within FP with 95% confidence over sequences (rafd.eval.far_threshold),
    the near threshold kept -> written into the checkpoint's meta. CalibrationError when none does."""
    from rafd.eval.far_threshold import calibrate_far as choose
    from rafd.model.checkpoint import read_checkpoint, save_checkpoint
    from rafd.protocol import FAR_THRESHOLD_KEY

    assert run.calibrate_far is not None
    from_m, budget = run.calibrate_far
    meta = dict(read_checkpoint(run.checkpoint)[2] or {})  # as --calibrate may have just written it
    near = operating_threshold(meta).near
    found = choose(
        [r.predictions for r in results], [r.ground_truth for r in results], [r.sequence for r in results],
        near, from_m, budget,
    )  # fmt: skip
    if not math.isfinite(found.threshold):
        raise CalibrationError(
            f"no far threshold keeps the whole scans within {budget:g} false positives per frame (95% upper bound)"
        )
    meta[FAR_THRESHOLD_KEY] = {"from_m": from_m, "threshold": found.threshold}
    meta["operating_point_far"] = {
        "rule": "the lowest threshold from from_m outwards whose whole-scan false positives per frame have a 95% "
        "upper bound (bootstrap over sequences) within the budget, the near threshold kept",
        "fp_per_frame_budget": budget,
        "fp_per_frame": found.fp_per_frame,
        "fp_per_frame_upper_bound": found.fp_per_frame_bound,
        "recall_beyond": 100.0 * found.recall_beyond,
        "data": str(run.data),
        "split": list(run.split),
        "frames": found.frames,
        "sequences": found.sequences,
    }
    save_checkpoint(run.checkpoint, model, cfg, meta)  # CPU copies of the weights, unchanged
    threshold = operating_threshold(meta)
    return threshold, (
        f"far operating threshold {found.threshold:.3f} from {from_m:g} m (whole scans: {found.fp_per_frame:.2f} "
        f"false positives per frame, 95% upper bound {found.fp_per_frame_bound:.2f} <= {budget:g}; recall beyond "
        f"{from_m:g} m {100 * found.recall_beyond:.1f}%) written into {run.checkpoint}"
    )


def flow_figures(results: Sequence[Any], overall: dict[str, Any], full_scan: bool) -> dict[str, Any]:
    """report["flow"]: the newest pairs' flow split into vehicle / background cells and by ring from the crop's
    edge, plus the label-free check (rafd.eval.flow_split); its vehicle_epe is overall's epe_foreground itself."""
    from rafd.eval.flow_split import flow_report, pooled

    return flow_report(
        pooled(getattr(r, "flow_tally", None) for r in results),
        vehicle_epe=overall.get("epe_foreground"),
        mode="full_scan_tiles" if full_scan else "crop",
    )


def write_plots(
    folder: Path,
    model: Any,
    cfg: Any,
    dataset: Any,
    results: Sequence[Any],
    examples: int,
    device: Any,
    score_threshold: OperatingThreshold,
) -> list[Path]:
    """Precision-recall plot of all frames and a few example frames (GT green, predictions red, flow). The examples
    draw what the service would answer: the boxes at or above `score_threshold` (the operating threshold, or
    --score-threshold), stated in each picture's legend, and flow arrows only in cells whose validity reaches
    FLOW_VALID_MIN (rafd.flow_validity, from the window's newest pair of poses)."""
    import cv2
    import numpy as np
    from torch.utils.data import Subset

    from rafd.detections import answered
    from rafd.eval.metrics import precision_recall
    from rafd.eval.predict import predict
    from rafd.flow_validity import config_validity
    from rafd.geometry import relative_pose
    from rafd.viz.plots import draw_detections, plot_precision_recall

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    pr_path = folder / "precision_recall.png"
    predictions, ground_truths = [r.predictions for r in results], [r.ground_truth for r in results]
    curves = {t: precision_recall(predictions, ground_truths, t) for t in IOU_THRESHOLDS}
    plot_precision_recall(curves, pr_path)
    written.append(pr_path)
    if examples > 0 and len(dataset):
        # Frames that hold objects make better examples; fall back to any frame.
        with_objects = [i for i, r in enumerate(results) if len(r.ground_truth)] or list(range(len(results)))
        picks = sorted(
            {with_objects[int(k)] for k in np.linspace(0, len(with_objects) - 1, min(examples, len(with_objects)))}
        )
        example_results = predict(
            model, Subset(dataset, picks), cfg, device, batch_size=len(picks), keep_flow=True, progress=False
        )
        for index, result in zip(picks, example_results):
            window = dataset[index]
            image = np.asarray(window["frames"])[-1].squeeze()  # [H, W] newest frame
            poses = np.asarray(window["poses"], np.float64)  # [T, 3]
            validity = config_validity(cfg, relative_pose(poses[-2], poses[-1]) if len(poses) > 1 else None)
            shown = answered(result.predictions, score_threshold)  # AP keeps all K; the service not
            canvas = draw_detections(
                image,
                gt_boxes=result.ground_truth,
                pred_boxes=shown[:, :5],
                pred_scores=shown[:, 5],
                resolution=cfg.resolution,
                flow=result.flow,
                upscale=4,  # 128 px crops are too small to read the boxes at 1:1
                score_threshold=score_threshold.near,
                validity=validity,
            )
            path = folder / f"example_{result.sequence}_{result.frame:06d}.png"
            if not cv2.imwrite(str(path), canvas):
                raise OSError(f"could not write {path}")
            written.append(path)
    return written


def evaluate(run: EvalRun) -> dict[str, Any]:
    """Score `run.checkpoint` on `run.data` as `run` says; write what it asks for (JSON, plots, MCAP, detections,
    the calibrated threshold) -> the report: overall, per sequence and per condition figures, and the paths written
    ("plots", "mcap", "detections", "json"), plus "calibration" (a line) after --calibrate. Raises EvalError when the
    run cannot be done (CalibrationError: no threshold within the budget)."""
    check_run(run)
    if run.mcap is not None:
        try:
            from rafd.eval.mcap import write_evaluation_logs
        except ImportError as error:
            raise EvalError(f"--mcap needs the logs extra (pip install 'rafd[logs]'): {error}") from error
    import torch

    from rafd.data.windows import DatasetError, open_windows
    from rafd.eval.predict import predict, summarise, summarise_by_condition, summarise_by_sequence
    from rafd.model.checkpoint import load_checkpoint
    from rafd.model.device import resolve_device

    try:
        device = resolve_device(run.device)
        model, cfg, meta = load_checkpoint(run.checkpoint, map_location="cpu")
        threshold = operating_threshold(meta, run.score_threshold)
        data_cfg = cfg
        if run.full_scan:
            from rafd.eval.fullscan import scan_config, scan_size_of

            data_cfg = scan_config(cfg, scan_size_of(run.data, list(run.split)))
        dataset = open_windows(
            run.data,
            list(run.split),
            data_cfg,
            run.max_windows,
            augment=False,
            cache=run.cache,
            estimate_poses=run.estimate_poses,
            history=run.like_frames,
            warm_up=run.warm_up_windows,
        )
    except (DatasetError, ValueError, RuntimeError) as error:
        raise EvalError(str(error)) from error
    if run.threads:
        torch.set_num_threads(run.threads)
    model = model.to(device).eval()
    try:
        if run.full_scan:
            from rafd.eval.fullscan import predict_full_scan

            results = predict_full_scan(
                model, dataset, cfg, device, precision=run.precision, progress=run.progress, keep_flow=run.tracking
            )
        else:
            results = predict(
                model,
                dataset,
                cfg,
                device,
                batch_size=run.batch_size,
                progress=run.progress,
                precision=run.precision,
                keep_flow=run.mcap is not None or run.tracking,
                past_as_newest=run.past_as_newest,
            )
    except ValueError as error:
        raise EvalError(str(error)) from error
    report: dict[str, Any] = {}
    if run.calibrate is not None:
        threshold, report["calibration"] = calibrate(run, results, cfg, model, meta)
    if run.calibrate_far is not None:
        threshold, report["calibration_far"] = calibrate_far(run, results, cfg, model)
    conditions = {sequence.name: sequence.condition for sequence in dataset.sequences}
    report.update(
        {
            "checkpoint": str(run.checkpoint),
            "data": str(run.data),
            "split": list(run.split),
            "num_frames": cfg.num_frames,
            "like_frames": run.like_frames,
            "input_size": cfg.input_size,
            "full_scan": run.full_scan,
            "past_as_newest": run.past_as_newest,
            "overall": summarise(results, score_threshold=threshold),
            "per_sequence": summarise_by_sequence(results, score_threshold=threshold),
            "per_condition": summarise_by_condition(results, conditions, score_threshold=threshold),
            "checkpoint_meta": {k: meta.get(k) for k in ("epoch", "step") if isinstance(meta, dict)},
        }
    )
    report["flow"] = flow_figures(results, report["overall"], run.full_scan)
    if run.tracking:
        from rafd.eval.tracking import evaluate_tracking
        from rafd.eval.tracking_inputs import tracking_frames

        frames, truth = tracking_frames(results, dataset, cfg, run.full_scan)
        report["tracking"] = evaluate_tracking(frames, threshold, velocity_truth=truth)
    if run.plots is not None:
        written = write_plots(run.plots, model, cfg, dataset, results, run.examples, device, threshold)
        report["plots"] = [str(p) for p in written]
    if run.mcap is not None:
        report["mcap"] = [str(p) for p in write_evaluation_logs(run.mcap, dataset, results, cfg, str(run.checkpoint))]
    if run.detections is not None:
        from rafd.eval.compare import save_detections

        save_detections(run.detections, results)
        report["detections"] = str(run.detections)
    if run.json is not None:
        run.json.parent.mkdir(parents=True, exist_ok=True)
        saved = {k: v for k, v in report.items() if k not in ("calibration", "calibration_far")}
        run.json.write_text(json.dumps(jsonable(saved), indent=2))
        report["json"] = str(run.json)
    return report
