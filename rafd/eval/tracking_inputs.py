"""What the tracking evaluation reads per scan (torch-free): one TrackingFrame per evaluated scan, with the detections,
the labelled vehicles with their ids and true velocities, the world pose, the time and the newest pair's flow as
rafd.tracking FlowFields (the crop's one, or a whole scan's tiles: flow_mosaic)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rafd.data.dataset import objects_in_crop
from rafd.eval.velocity_truth import Truth, label_velocities, simulated_velocities
from rafd.flow_validity import config_validity, search_reach_m
from rafd.geometry import relative_pose
from rafd.tracking import FlowField, FlowGrid


@dataclass(frozen=True)
class TrackingFrame:
    sequence: str
    frame: int  # the scan's frame number
    timestamp: float  # seconds
    pose: np.ndarray  # [3] world pose
    detections: np.ndarray  # [N, 6] (x, y, width, length, yaw, score), ego frame, outside ignore regions
    truth: np.ndarray  # [M, 5] labelled vehicles
    truth_ids: np.ndarray  # [M] int64
    truth_velocity: np.ndarray  # [M, 2] m/s ego axes; NaN where unknown
    ignore: np.ndarray  # [K, 5] regions the labeller left undecided (and, for real scans, outside the labelled area)
    flow: tuple[FlowField, ...] | None  # the newest real pair's flow; None without one
    condition: str | None = None  # weather (simulated) or RADIATE's type


def reach_of(cfg: Any) -> float:
    """A config's flow search reach per pair, metres (rafd.flow_validity.search_reach_m)."""
    return search_reach_m(cfg.flow.stride, cfg.resolution, cfg.flow.local_radius)


def flow_mosaic(
    tiles: Any, flows: np.ndarray, relative: np.ndarray, cfg: Any, interval_s: float
) -> tuple[FlowField, ...]:
    """Newest pair flow by tiles (rafd.runtime.view.View; flows [V, 2, Hf, Wf] metres in each tile's frame =
    the ego axes shifted, each tile's relative pose [V, 3]) -> one FlowField per stepped tile."""
    height, width = flows.shape[-2:]
    cell = cfg.input_size * cfg.resolution / width
    reach = reach_of(cfg)
    return tuple(
        FlowField(
            FlowGrid.centred(height, width, cell, (float(offset[0]), float(offset[1]))),
            np.asarray(flows[t], np.float32),
            interval_s,
            config_validity(cfg, relative[t]),
            reach,
        )
        for t, offset in enumerate(tiles.offsets_m)
    )


def crop_flow(flow: np.ndarray, relative: np.ndarray, cfg: Any, interval_s: float) -> tuple[FlowField, ...]:
    """The model's crop flow [2, Hf, Wf] (centred on the radar) and the pair's relative pose [3] -> one FlowField."""
    height, width = flow.shape[-2:]
    cell = cfg.input_size * cfg.resolution / width
    grid = FlowGrid.centred(height, width, cell)
    return (FlowField(grid, np.asarray(flow, np.float32), interval_s, config_validity(cfg, relative), reach_of(cfg)),)


def sequence_truth(meta: Any) -> tuple[Truth, str]:
    """A dataset sequence's true velocities -> (per frame {id: [2]}, "simulator" | "labels")."""
    folder = Path(meta.frames[0].image_path).parents[1] if meta.frames else None
    simulated = simulated_velocities(folder, meta.numbers) if folder is not None else None
    if simulated is not None:
        return simulated, "simulator"
    return label_velocities(meta.boxes, meta.ids, meta.poses, meta.timestamps, meta.numbers), "labels"


def tracking_frames(results: Sequence[Any], dataset: Any, cfg: Any, full_scan: bool) -> tuple[list[TrackingFrame], str]:
    """FrameResults (rafd.eval.predict / fullscan, with their flow kept) and their dataset -> the TrackingFrames in
    stream order (sequence, frame number), and where the true velocities came from."""
    metas = {meta.name: meta for meta in dataset.sequences}
    truths = {name: sequence_truth(meta) for name, meta in metas.items()}
    frames = []
    for result in sorted(results, key=lambda r: (r.sequence, r.frame)):
        meta = metas[result.sequence]
        k = int(np.flatnonzero(meta.numbers == result.frame)[0])
        size = meta.image_size if full_scan else cfg.input_size
        boxes, ids, _, ignore = objects_in_crop(meta.boxes[k], meta.ids[k], meta.classes[k], size, cfg.resolution)
        velocities = truths[result.sequence][0][k]
        truth_velocity = np.array([velocities.get(int(i), (np.nan, np.nan)) for i in ids], np.float64).reshape(-1, 2)
        frames.append(
            TrackingFrame(
                sequence=result.sequence,
                frame=int(result.frame),
                timestamp=float(meta.timestamps[k]),
                pose=np.asarray(meta.poses[k], np.float64),
                detections=np.asarray(result.predictions, np.float64).reshape(-1, 6),
                truth=np.asarray(boxes, np.float64).reshape(-1, 5),
                truth_ids=np.asarray(ids, np.int64),
                truth_velocity=truth_velocity,
                ignore=np.asarray(ignore, np.float64).reshape(-1, 5),
                flow=_frame_flow(result, meta, k, cfg, full_scan),
                condition=meta.condition,
            )
        )
    sources = sorted({source for _, source in truths.values()})
    return frames, "+".join(sources)


def _frame_flow(result: Any, meta: Any, k: int, cfg: Any, full_scan: bool) -> tuple[FlowField, ...] | None:
    if full_scan:
        return getattr(result, "flow_fields", None)
    if result.flow is None or k == 0 or meta.numbers[k] - meta.numbers[k - 1] != 1:
        return None  # a stream's first scan: its "pair" is the scan with itself (a warm-up window)
    relative = relative_pose(meta.poses[k - 1], meta.poses[k])
    return crop_flow(result.flow, relative, cfg, float(meta.timestamps[k] - meta.timestamps[k - 1]))
