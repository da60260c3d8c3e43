"""Full-scan evaluation: the PyTorch model streamed over whole scans in tiles (rafd.eval.tiled), merged at tile borders.

The dataset is opened at the scan's own size (no crop, so every annotated vehicle counts, not only those inside the
protocol's 256 px crop). Each sequence is walked frame by frame like a stream: a frame's tiles are encoded once,
each tile's newest pair flow is computed once (model.encode_frame / pair_flow, the decomposition the exported step
graph uses), the last T of them are kept per tile, and every window of the dataset is detected from those caches
(model.detect) -- the same result as running each tile's window, T times cheaper.

No flow targets are built for whole scans; each frame's FrameResult carries the label-free flow check of its newest
pair over every tile (rafd.eval.flow_split), its rings counted from each tile's own edge: the model sees each tile
as a crop, so that is the edge its matching is cut at (inner tile edges included, where the scan goes on).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import torch

from rafd.config import RaFDConfig
from rafd.data.dataset import objects_in_crop
from rafd.eval.flow_split import FlowTally, pooled, tally_pair
from rafd.eval.predict import FrameResult, outside_ignored
from rafd.eval.tiled import TileGrid, merge_tiles, tile_poses
from rafd.eval.tracking_inputs import flow_mosaic
from rafd.flow_validity import config_validity
from rafd.model import RaFD, relative_pose_torch
from rafd.model.precision import autocast
from rafd.preprocess import to_model_input
from rafd.progress import bar as progress_bar


def scan_config(cfg: RaFDConfig, scan_size: int) -> RaFDConfig:
    """What the dataset needs to hand out whole scans: the model's config at the scan's size (the dataset reads only
    the input size, frames and resolution; no model is built from it)."""
    return cfg.replace(input_size=scan_size)


def scan_size_of(root, split) -> int:
    """Side in pixels of the scans of the first sequence of `split` under `root` (all must share it)."""
    from rafd.data.dataset import select_sequences
    from rafd.data.folders import list_frames

    folders, seen = select_sequences(root, split)
    if not folders:
        raise ValueError(f"no sequence of split {split!r} under {root} (splits: {seen})")
    return list_frames(folders[0]).image_size


@torch.no_grad()
def predict_full_scan(
    model: RaFD,
    dataset: Any,
    cfg: RaFDConfig,
    device: torch.device | str = "cpu",
    grid: TileGrid | None = None,
    precision: str = "fp32",
    tiles_per_batch: int = 32,
    progress: bool = True,
    keep_flow: bool = False,
) -> list[FrameResult]:
    """Every window of a whole-scan RadarWindowDataset (opened with scan_config) -> FrameResults with the merged
    detections of the whole newest scan (ego frame, all K of every tile kept: AP wants the tail); keep_flow also
    keeps each scan's newest real pair's flow as a mosaic of the tiles' flow fields (FrameResult.flow_fields)."""
    device = torch.device(device)
    model.eval()
    frames_per_window = cfg.num_frames
    # a WindowSubset (--max-windows) names some windows of the dataset it wraps
    base = getattr(dataset, "dataset", dataset)
    windows = [base.windows[i] for i in dataset.indices] if base is not dataset else dataset.windows
    wanted = {(s, start + frames_per_window - 1) for s, start in windows}  # (sequence, newest position)
    # the frames those windows hold: the others are skipped (a skip restarts the stream like a gap; every wanted
    # window still streams all its frames, so its figures are those of the whole stream)
    needed = {(s, k - back) for s, k in wanted for back in range(frames_per_window)}
    results = []

    def batched(function, *tensors: torch.Tensor) -> torch.Tensor:
        outputs = []
        for start in range(0, len(tensors[0]), tiles_per_batch):
            with autocast(device, precision):
                outputs.append(function(*(t[start : start + tiles_per_batch] for t in tensors)))
        return torch.cat(outputs)

    bar = progress_bar(total=len(wanted), desc="predict full scans", unit="scan", enabled=progress)
    for s, meta in enumerate(dataset.sequences):
        features: deque = deque(maxlen=frames_per_window)  # per frame: [n, C, Hf, Wf]
        flows: deque = deque(maxlen=max(frames_per_window - 1, 1))  # per pair: [n, 2, Hf, Wf]
        poses: deque = deque(maxlen=frames_per_window)  # per frame: [n, 3] tile world poses
        newest_relative = None  # [n, 3] ego motion of flows[-1], the newest real pair
        previous_number = None
        previous_time = None  # timestamp of the frame before the newest (the newest pair's older scan)
        interval = math.nan  # seconds between the newest pair's scans
        for k, number in enumerate(meta.numbers):
            if (s, k) not in needed:
                previous_number = None  # the stream starts again at the next frame needed
                features.clear()
                flows.clear()
                poses.clear()
                newest_relative = None
                continue
            if previous_number is not None and number != previous_number + 1:  # a gap: the stream starts again
                features.clear()
                flows.clear()
                poses.clear()
                newest_relative = None
            previous_number = number
            scan = base._scan(s, k)
            tiles = grid or TileGrid.for_model(cfg.input_size, scan_size=scan.shape[0], resolution=cfg.resolution)
            crops = torch.from_numpy(to_model_input(tiles.crops(scan)))[:, None].to(device)  # [n, 1, S, S]
            pose = torch.from_numpy(tile_poses(meta.poses[k], tiles.offsets_m).astype(np.float64))  # [n, 3]
            encoded = batched(model.encode_frame, crops).float()
            if features and frames_per_window > 1:
                relative = relative_pose_torch(poses[-1], pose).float().to(device)  # [n, 3]
                flows.append(batched(model.pair_flow, features[-1], encoded, relative).float())
                newest_relative = relative.double().cpu().numpy()
                interval = float(meta.timestamps[k] - previous_time) if previous_time is not None else math.nan
            previous_time = float(meta.timestamps[k])
            features.append(encoded)
            poses.append(pose)
            if (s, k) not in wanted:
                continue
            window_features, window_pose_list, window_flows = list(features), list(poses), list(flows)
            real_pair = bool(flows)  # else the newest pair is a warm-up window's padding: a frame with itself
            missing = frames_per_window - len(window_features)
            if missing > 0:
                # a warm-up window (the dataset's warm_up): the old end padded by repeating the oldest frame at its
                # pose, as the dataset and the service pad a stream's first frames; its pairs' flow as the model
                # computes it between two identical frames
                oldest, oldest_pose = window_features[0], window_pose_list[0]
                still = relative_pose_torch(oldest_pose, oldest_pose).float().to(device)  # [n, 3] zeros
                repeated = batched(model.pair_flow, oldest, oldest, still).float()
                window_features = [oldest] * missing + window_features
                window_pose_list = [oldest_pose] * missing + window_pose_list
                window_flows = [repeated] * missing + window_flows
            window_poses = torch.stack(window_pose_list, 1).float().to(device)  # [n, T, 3]
            stacked = torch.stack(window_features, 1)  # [n, T, C, Hf, Wf]
            pair_flows = torch.stack(window_flows, 1) if frames_per_window > 1 else None  # [n, T-1, 2, Hf, Wf]
            boxes, scores = [], []
            for start in range(0, len(stacked), tiles_per_batch):
                part = slice(start, start + tiles_per_batch)
                with autocast(device, precision):
                    out = model.detect(
                        stacked[part], None if pair_flows is None else pair_flows[part], window_poses[part]
                    )
                boxes.append(out["boxes"].float().cpu().numpy())
                scores.append(out["scores"].float().cpu().numpy())
            found = merge_tiles(tiles, np.concatenate(boxes), np.concatenate(scores))
            tally = None
            if pair_flows is not None:
                tally = _tile_tally(
                    pair_flows[:, -1].cpu().numpy(), newest_relative if real_pair else None, cfg, not real_pair
                )
            truth, _, _, ignore = objects_in_crop(
                meta.boxes[k], meta.ids[k], meta.classes[k], scan.shape[0], cfg.resolution
            )
            results.append(
                FrameResult(
                    sequence=meta.name,
                    frame=int(number),
                    predictions=outside_ignored(found.as_array(), ignore),
                    ground_truth=truth,
                    epe_all=math.nan,
                    epe_foreground=math.nan,
                    cells_all=0,
                    cells_foreground=0,
                    flow_tally=tally,
                    flow_fields=flow_mosaic(tiles, pair_flows[:, -1].cpu().numpy(), newest_relative, cfg, interval)
                    if keep_flow and real_pair and pair_flows is not None and newest_relative is not None
                    else None,
                )
            )
            bar.update(1)
    bar.close()
    return results


def _tile_tally(flows: np.ndarray, relative: np.ndarray | None, cfg: RaFDConfig, repeated: bool) -> FlowTally:
    """The newest pair's flow of every tile [n, 2, Hf, Wf] and their ego motions [n, 3] (None: identity) -> the
    label-free FlowTally of the whole scan (rings from each tile's edge; one pair per scan)."""
    tiles = [
        tally_pair(flow, config_validity(cfg, None if relative is None else relative[t]), repeated=repeated)
        for t, flow in enumerate(flows)
    ]
    total = pooled(tiles)
    total.pairs, total.repeated_pairs = 1, int(repeated)
    return total
