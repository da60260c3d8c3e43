"""Pseudo-GT flow of a simulated sequence, read back through RadarWindowDataset, against the simulator's
true object motion (computed here from the in-memory simulation, not from the files).

Two figures (run with -s to print them):
- centre EPE: the flow at each matched object's centre cell vs the true displacement of its centre with ego
  motion removed: only float32 rounding may separate them (the files round-trip the boxes exactly);
- region EPE: every foreground cell vs the true rigid-body motion of the object's material at that cell
  (objects turn, so points off the centre move slightly differently from the centre): the price of the
  paper's constant-displacement region, small against the motion itself.
"""

from __future__ import annotations

import math

import numpy as np

from rafd.config import RaFDConfig
from rafd.data import RadarWindowDataset
from rafd.data.targets import build_targets, flow_radius
from rafd.geometry import feature_cell_centres

CFG = RaFDConfig.tiny(input_size=256)  # 64 x 64 cells of 0.694 m (+-22 m), 4 frames


def _matrix(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:2, :2].T + matrix[:2, 2]


def test_pseudo_gt_flow_matches_the_simulated_motion(sim_truth_and_folder) -> None:
    truth, folder = sim_truth_and_folder
    dataset = RadarWindowDataset(folder, split="train_good_weather", cfg=CFG)
    assert len(dataset) == len(truth.images) - CFG.num_frames + 1
    size, cell = CFG.feature_size, CFG.cell_size
    cells = feature_cell_centres(size, CFG.input_size, CFG.resolution)  # [Hf, Wf, 2]
    grid_i, grid_j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    by_id = {o.id: o for o in truth.objects}
    centre_errors, region_errors, motions = [], [], []
    for index in range(len(dataset)):
        window = dataset[index]
        start = window["frame"] - CFG.num_frames  # window position of the oldest frame (numbers start at 1)
        targets = build_targets(window["boxes"], window["ids"], window["poses"], CFG)
        for pair in range(CFG.num_frames - 1):
            t = start + pair + 1  # truth index of the later frame
            ego_prev, ego_cur = _matrix(*truth.poses[t - 1]), _matrix(*truth.poses[t])
            prev_to_cur = np.linalg.inv(ego_cur) @ ego_prev
            ids_prev = set(window["ids"][pair].tolist())
            regions = []
            for object_id, box in zip(window["ids"][pair + 1].tolist(), window["boxes"][pair + 1]):
                row, col = int(math.floor(size / 2 - box[1] / cell)), int(math.floor(box[0] / cell + size / 2))
                sigma = flow_radius(box, CFG)
                regions.append((object_id, row, col, np.hypot(grid_i - row, grid_j - col) <= sigma))
            for object_id, row, col, region in regions:
                if object_id not in ids_prev:
                    continue
                alone = region & ~np.any(
                    [r for o, _, _, r in regions if o != object_id] or [np.zeros_like(region)], axis=0
                )
                if not alone[row, col]:
                    continue  # shares its centre cell's region with another object
                obj = by_id[object_id]
                box_prev, box_cur = obj.boxes[t - 1], obj.boxes[t]
                true_motion = box_cur[:2] - _apply(prev_to_cur, box_prev[:2])
                flow = targets["flow"][pair]  # [2, Hf, Wf]
                centre_errors.append(np.hypot(*(flow[:, row, col] - true_motion)))
                motions.append(np.hypot(*true_motion))
                if motions[-1] < 0.1:
                    continue  # parked: region figures over moving objects only
                # Rigid-body motion of the object's material at each cell of its region.
                material_now = cells[alone]  # [n, 2] in frame t
                to_body = np.linalg.inv(_matrix(box_cur[0], box_cur[1], box_cur[4]))
                from_body_prev = _matrix(box_prev[0], box_prev[1], box_prev[4])
                was = _apply(prev_to_cur @ from_body_prev @ to_body, material_now)
                region_errors.extend(np.hypot(*(flow[:, alone].T - (material_now - was)).T))
                assert np.all(targets["flow_foreground"][pair, 0][alone] == 1.0)
            background = ~np.any([r for _, _, _, r in regions] or [np.zeros((size, size), bool)], axis=0)
            assert np.all(targets["flow"][pair][:, background] == 0.0)
    centre_errors, region_errors, motions = map(np.array, (centre_errors, region_errors, motions))
    moving = motions[motions >= 0.1]
    print(
        f"\npseudo-GT flow vs simulated motion: {len(motions)} matched objects ({len(moving)} moving, mean motion "
        f"{moving.mean():.3f} m per frame pair); "
        f"centre EPE mean {centre_errors.mean():.2e} max {centre_errors.max():.2e} m; "
        f"region EPE ({len(region_errors)} cells) mean {region_errors.mean():.2e} "
        f"p95 {np.percentile(region_errors, 95):.2e} "
        f"max {region_errors.max():.2e} m"
    )
    assert len(moving) >= 10 and moving.mean() > 0.5  # moving traffic, not a trivial scene
    assert centre_errors.max() < 1e-4
    assert region_errors.mean() < 0.05 * moving.mean() and region_errors.max() < 0.25
