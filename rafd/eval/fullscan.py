"""Full-scan evaluation: the PyTorch model streamed over whole scans as the service streams its ONNX graph.

The dataset is opened at the scan's own size (no crop, so every annotated vehicle counts, not only those inside the
protocol's 256 px crop). Each sequence is walked frame by frame like a stream, through the same code as the service:
the whole view's tiles (rafd.runtime.view) stepped by rafd.runtime.StreamRunner, here on the model's own step
(rafd.eval.torch_backend), merged at tile borders; every window of the dataset is the stream's window at its newest
frame.

No flow targets are built for whole scans; each frame's FrameResult carries the label-free flow check of its newest
pair over every tile (rafd.eval.flow_split), its rings counted from each tile's own edge: the model sees each tile
as a crop, so that is the edge its matching is cut at (inner tile edges included, where the scan goes on).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from rafd.config import RaFDConfig
from rafd.data.dataset import objects_in_crop
from rafd.eval.flow_split import FlowTally, pooled, tally_pair
from rafd.eval.predict import FrameResult, outside_ignored
from rafd.eval.torch_backend import TorchBackend
from rafd.eval.tracking_inputs import flow_mosaic
from rafd.flow_validity import config_validity
from rafd.geometry import relative_pose
from rafd.model import RaFD
from rafd.progress import bar as progress_bar
from rafd.runtime import StreamRunner
from rafd.runtime.view import View, step_view


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


def predict_full_scan(
    model: RaFD,
    dataset: Any,
    cfg: RaFDConfig,
    device: torch.device | str = "cpu",
    precision: str = "fp32",
    progress: bool = True,
    keep_flow: bool = False,
    range_m: float | None = None,
) -> list[FrameResult]:
    """Every window of a whole-scan RadarWindowDataset (opened with scan_config) -> FrameResults with the merged
    detections of the newest view (rafd.runtime.view: whole scan, or within `range_m` of the radar; ego frame, all
    K of every tile kept: AP wants the tail); keep_flow also keeps each scan's newest real pair's flow as the tiles'
    FlowFields (FrameResult.flow_fields)."""
    runner = StreamRunner(TorchBackend(model, cfg, device, precision))
    frames_per_window = cfg.num_frames
    # a WindowSubset (--max-windows) names some windows of the dataset it wraps
    base = getattr(dataset, "dataset", dataset)
    windows = [base.windows[i] for i in dataset.indices] if base is not dataset else dataset.windows
    wanted = {(s, start + frames_per_window - 1) for s, start in windows}  # (sequence, newest position)
    # the frames those windows hold: the others are skipped (a skip restarts the stream like a gap; every wanted
    # window still streams all its frames, so its figures are those of the whole stream)
    needed = {(s, k - back) for s, k in wanted for back in range(frames_per_window)}
    cell_px = cfg.input_size // cfg.feature_size
    results = []
    bar = progress_bar(total=len(wanted), desc="predict full scans", unit="scan", enabled=progress)
    for s, meta in enumerate(dataset.sequences):
        state = runner.new_state()
        previous: tuple[int, float, np.ndarray] | None = None  # (frame number, timestamp, tile poses) of the last
        for k, number in enumerate(meta.numbers):
            if (s, k) not in needed or (previous is not None and number != previous[0] + 1):
                state, previous = runner.new_state(), None  # a gap: the stream starts again
            if (s, k) not in needed:
                continue
            scan = base._scan(s, k)
            view = View.of(scan.shape[0], cfg.input_size, cfg.resolution, cell_px, range_m)
            poses = view.tile_poses(meta.poses[k])  # [V, 3]
            result, state = step_view(runner, state, view, scan, meta.poses[k])
            relative = None if previous is None else relative_pose(previous[2], poses)  # [V, 3] the pair's motion
            interval = math.nan if previous is None else float(meta.timestamps[k] - previous[1])
            previous = (number, float(meta.timestamps[k]), poses)
            if (s, k) not in wanted:
                continue
            found = view.merge(result.boxes, result.scores)
            tally = flow_fields = None
            if result.flow is not None:
                tally = _tile_tally(result.flow, relative, cfg, relative is None)
                if keep_flow and relative is not None:
                    flow_fields = flow_mosaic(view, result.flow, relative, cfg, interval)
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
                    flow_fields=flow_fields,
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
