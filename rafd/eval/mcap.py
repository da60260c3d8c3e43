"""rafd-eval --mcap: the evaluated windows as Foxglove/MCAP logs, one file per sequence (rafd.viz.mcap topics).

Each window's newest frame is logged once, in time order: the model's input crop as the scan, its ego pose,
the predictions above the score threshold, the newest pair's flow (its valid cells only: rafd.flow_validity), and
the benchmark protocol's ground truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from rafd.flow_validity import FLOW_VALID_MIN, config_validity
from rafd.geometry import box_polygons_pixels, feature_cell_centres, relative_pose
from rafd.protocol import DEFAULT_SCORE_THRESHOLD
from rafd.viz.mcap import LoggedFrame, RadarMcapLog

LOG_SCORE = DEFAULT_SCORE_THRESHOLD  # predictions logged (AP keeps all K, a log cannot)


def evaluation_frame(window: dict[str, Any], result: Any, cfg: Any, score_threshold: float = LOG_SCORE) -> LoggedFrame:
    """One window (RadarWindowDataset item) and its FrameResult -> the LoggedFrame of its newest frame."""
    crop = np.ascontiguousarray(np.asarray(window["frames"])[-1], dtype=np.uint8)  # [S, S] the model's input
    size, resolution = crop.shape[0], float(cfg.resolution)
    ok, png = cv2.imencode(".png", crop)
    if not ok:
        raise OSError(f"could not encode frame {result.frame} of {result.sequence}")
    shown = result.predictions[result.predictions[:, 5] >= score_threshold]  # [N, 6] best first
    heads = motions = None
    if result.flow is not None:
        flow = np.asarray(result.flow, dtype=np.float64)  # [2, Hf, Wf]
        heads = feature_cell_centres(flow.shape[1], size, resolution).reshape(-1, 2)  # [Hf*Wf, 2] metres
        motions = np.moveaxis(flow, 0, -1).reshape(-1, 2)  # [Hf*Wf, 2]
        moving = np.hypot(motions[:, 0], motions[:, 1]) > 0.05  # cells moving less than 5 cm are not drawn
        poses = np.asarray(window["poses"], np.float64)  # [T, 3]
        if flow.shape[1] == cfg.feature_size and len(poses) > 1:  # the model's crop: its flow validity applies
            moving &= config_validity(cfg, relative_pose(poses[-2], poses[-1])).reshape(-1) >= FLOW_VALID_MIN
        heads, motions = heads[moving], motions[moving]
    truth = np.asarray(result.ground_truth, dtype=np.float64).reshape(-1, 5)
    return LoggedFrame(
        timestamp_ns=round(float(np.asarray(window["timestamps"])[-1]) * 1e9),
        scan_png=png.tobytes(),
        scan_size=size,
        resolution=resolution,
        crop=(0, size),
        crop_pixels=crop,
        pose=np.asarray(window["poses"], np.float64)[-1],
        boxes=shown[:, :5],
        scores=shown[:, 5],
        classes=[cfg.class_names[0]] * len(shown),
        polygons=box_polygons_pixels(shown[:, :5], size, resolution),
        flow_heads=heads,
        flow_motions=motions,
        truth_boxes=truth,
        truth_polygons=box_polygons_pixels(truth, size, resolution),
    )


def write_evaluation_logs(
    folder: Path, dataset: Any, results: Sequence[Any], cfg: Any, checkpoint: str, score_threshold: float = LOG_SCORE
) -> list[Path]:
    """results[i] belongs to dataset[i] (predict keeps the order) -> folder/<sequence>.mcap per sequence."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    by_sequence: dict[str, list[int]] = {}
    for index, result in enumerate(results):
        by_sequence.setdefault(result.sequence, []).append(index)
    paths = []
    for name, indices in sorted(by_sequence.items()):
        path = folder / f"{''.join(c if c.isalnum() or c in '._-' else '_' for c in name)}.mcap"
        with RadarMcapLog(path) as log:
            for index in sorted(indices, key=lambda i: results[i].frame):
                log.write(evaluation_frame(dataset[index], results[index], cfg, score_threshold))
            log.write_metadata(
                "rafd-eval",
                {
                    "sequence": name,
                    "checkpoint": checkpoint,
                    "frames": log.frames,
                    "input_size": cfg.input_size,
                    "num_frames": cfg.num_frames,
                    "score_threshold": score_threshold,
                },
            )
        paths.append(path)
    return paths
