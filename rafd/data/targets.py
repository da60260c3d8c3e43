"""Training targets of one window: CenterNet heatmap + box regression (newest frame) and pseudo-GT flow.

Grid (contract): feature cell (i, j) centre at x = (j + 0.5 - Wf/2) * c, y = (Hf/2 - i - 0.5) * c metres,
c = cfg.cell_size; flat index i * Wf + j. A box centre (x, y) lies in cell j = floor(x / c + Wf/2),
i = floor(Hf/2 - y / c); centres outside the grid get no target (counted in a log warning).

Heatmap: CenterNet's draw_umich_gaussian: radius r = max(min_radius, int(gaussian_radius((l, w), min_overlap)))
with l, w the box's length and width in cells (cfg.targets: CenterPoint's 0.1 and 2 by default), sigma =
(2r + 1) / 6, peak exactly 1 at the centre cell, max over objects.

Box regression at the centre cell: offset to the exact centre (cells), log size and orientation as
cfg.head.box_encoding says: "symmetric" regresses the canonical box (canonical_boxes: width <= length, yaw taken
modulo 180 degrees) as log(width, length) and (sin 2yaw, cos 2yaw), so the 180-degree flips and width/length swaps
of real labels within one track are the same target; "as_labelled" regresses log(width, length) and
(sin yaw, cos yaw) as annotated.

Pseudo-GT flow (paper section 2.5), one map per consecutive pair (t-1, t), in frame t's grid: for each
object of frame t whose id also appears in frame t-1, its displacement
    d = c_t - T_{t-1 -> t}(c_{t-1}),  T_{t-1 -> t} = geometry.relative_pose(pose_{t-1}, pose_t)
(the frame-(t-1) centre moved into frame t's ego coordinates: ego motion removed) is written into every
cell of its Gaussian region: cells within sigma_flow = max(f(hw), gamma) cells (Euclidean, cell units) of
the object's centre cell, with f(hw) = gaussian_radius((l, w), cfg.targets.flow_min_overlap = 0.7) in cells and
gamma = cfg.targets.flow_min_radius = 2 cells (1.4 m at the paper's 0.69 m cells, about half a car length, so
even small or thin objects cover a few cells). Where regions overlap, the object whose
normalised distance (distance / sigma_flow) is smaller wins. Background is zero.
flow_foreground = 1 in the regions of matched objects. flow_valid = 1 everywhere except the regions of
objects present in frame t but not in t-1 (their motion is unknown: neither zero nor a displacement is a
correct target there).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from rafd.config import RaFDConfig
from rafd.geometry import feature_cell_centres, points_in_boxes, relative_pose, transform_points, wrap_angle

log = logging.getLogger(__name__)


def canonical_boxes(boxes: np.ndarray) -> np.ndarray:
    """[N, 5] boxes -> the same boxes (same corner sets) with width <= length and yaw in [-pi/2, pi/2).

    A box turned by 180 degrees, or with width and length swapped and turned by 90 degrees, covers the same
    rectangle; this picks one representative (rafd.model.boxes.decode_boxes returns the same form)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5).copy()
    swap = boxes[:, 2] > boxes[:, 3]
    boxes[swap, 2], boxes[swap, 3] = boxes[swap, 3].copy(), boxes[swap, 2].copy()
    boxes[swap, 4] += np.pi / 2.0
    boxes[:, 4] = wrap_angle(2.0 * boxes[:, 4]) / 2.0  # modulo pi, in [-pi/2, pi/2)
    return boxes


def gaussian_radius(height: float, width: float, min_overlap: float = 0.7) -> float:
    """CenterNet's radius (cells) such that a box shifted by it still overlaps the true box with IoU >= min_overlap
    (the three-case formula of CornerNet/CenterNet, as in their code)."""
    a1 = 1.0
    b1 = height + width
    c1 = width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1**2 - 4 * a1 * c1)) / 2
    a2 = 4.0
    b2 = 2 * (height + width)
    c2 = (1 - min_overlap) * width * height
    r2 = (b2 + math.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (height + width)
    c3 = (min_overlap - 1) * width * height
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def draw_gaussian(heatmap: np.ndarray, row: int, col: int, radius: int) -> None:
    """CenterNet draw_umich_gaussian: max-blend a (2r+1)^2 Gaussian (sigma = (2r+1)/6, peak 1) at (row, col)."""
    diameter = 2 * radius + 1
    sigma = diameter / 6.0
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    gaussian = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma * sigma))
    height, width = heatmap.shape
    top, bottom = min(row, radius), min(height - row, radius + 1)
    left, right = min(col, radius), min(width - col, radius + 1)
    patch = heatmap[row - top : row + bottom, col - left : col + right]
    np.maximum(patch, gaussian[radius - top : radius + bottom, radius - left : radius + right], out=patch)


def centre_cells(centres: np.ndarray, cfg: RaFDConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, 2] metres -> (rows [N] int, cols [N] int, inside [N] bool) of the cells holding them."""
    hf = wf = cfg.feature_size
    col_f = centres[:, 0] / cfg.cell_size + wf / 2.0
    row_f = hf / 2.0 - centres[:, 1] / cfg.cell_size
    cols, rows = np.floor(col_f).astype(np.int64), np.floor(row_f).astype(np.int64)
    inside = (rows >= 0) & (rows < hf) & (cols >= 0) & (cols < wf)
    return rows, cols, inside


def _object_radius(box: np.ndarray, cfg: RaFDConfig, min_overlap: float) -> float:
    """CenterNet radius of the box in cells (continuous)."""
    return gaussian_radius(box[3] / cfg.cell_size, box[2] / cfg.cell_size, min_overlap)


def heatmap_radius(box: np.ndarray, cfg: RaFDConfig) -> int:
    """Heatmap Gaussian radius of a box in cells: max(min_radius, int(gaussian_radius(l, w, min_overlap)))."""
    targets = cfg.targets
    return max(targets.heatmap_min_radius, int(_object_radius(box, cfg, targets.heatmap_min_overlap)))


def flow_radius(box: np.ndarray, cfg: RaFDConfig) -> float:
    """Pseudo-GT flow region radius of a box in cells: max(f(hw), gamma)."""
    targets = cfg.targets
    return max(_object_radius(box, cfg, targets.flow_min_overlap), targets.flow_min_radius)


def box_regression_targets(box: np.ndarray, cfg: RaFDConfig) -> tuple[tuple[float, float], tuple[float, float]]:
    """One box [5] -> (log size (2), orientation (2)) as cfg.head.box_encoding regresses them."""
    if cfg.head.box_encoding == "symmetric":
        box = canonical_boxes(box)[0]
        angle = 2.0 * box[4]
    else:
        angle = box[4]
    log_size = (math.log(max(box[2], 1e-3)), math.log(max(box[3], 1e-3)))
    return log_size, (math.sin(angle), math.cos(angle))


def _flow_pair(
    boxes_prev: np.ndarray,
    ids_prev: np.ndarray,
    pose_prev: np.ndarray,
    boxes_cur: np.ndarray,
    ids_cur: np.ndarray,
    pose_cur: np.ndarray,
    cfg: RaFDConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> flow [2, Hf, Wf], valid [1, Hf, Wf], foreground [1, Hf, Wf] for the pair (prev, cur) in cur's grid."""
    size = cfg.feature_size
    flow = np.zeros((2, size, size), np.float32)
    valid = np.ones((1, size, size), np.float32)
    foreground = np.zeros((1, size, size), np.float32)
    if len(boxes_cur) == 0:
        return flow, valid, foreground
    to_cur = relative_pose(pose_prev, pose_cur)  # maps frame t-1 ego coordinates into frame t's
    previous: dict[int, int] = {}
    for index, object_id in enumerate(ids_prev.tolist()):
        previous.setdefault(object_id, index)  # a repeated id: the first one (the reader warns about repeats)
    rows, cols, inside = centre_cells(boxes_cur[:, :2], cfg)
    best = np.full((size, size), np.inf)  # normalised distance of the region owning each cell
    for k in np.flatnonzero(inside):
        sigma = flow_radius(boxes_cur[k], cfg)
        # only the cells of the disc's bounding window: [top:bottom, left:right]
        reach = int(np.floor(sigma))
        top, bottom = max(rows[k] - reach, 0), min(rows[k] + reach + 1, size)
        left, right = max(cols[k] - reach, 0), min(cols[k] + reach + 1, size)
        window = (slice(top, bottom), slice(left, right))
        distance = (
            np.hypot(np.arange(top, bottom)[:, None] - rows[k], np.arange(left, right)[None, :] - cols[k]) / sigma
        )
        region = (distance <= 1.0) & (distance < best[window])
        if not region.any():
            continue
        best[window][region] = distance[region]
        match = previous.get(int(ids_cur[k]))
        if match is None:  # new in frame t: unknown motion
            flow[:, top:bottom, left:right][:, region] = 0.0
            valid[0][window][region] = 0.0
            foreground[0][window][region] = 0.0
            continue
        displacement = boxes_cur[k, :2] - transform_points(to_cur, boxes_prev[match, :2])
        flow[0][window][region], flow[1][window][region] = displacement[0], displacement[1]
        valid[0][window][region] = 1.0
        foreground[0][window][region] = 1.0
    return flow, valid, foreground


def build_targets(
    boxes: list[np.ndarray],
    ids: list[np.ndarray],
    poses: np.ndarray,
    cfg: RaFDConfig,
    ignore: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """T frames of boxes [M_t, 5] (metres, each frame's ego frame), ids [M_t] and world poses [T, 3] -> targets
    (see the module docstring and the DATA contract)."""
    num_frames = len(boxes)
    if len(ids) != num_frames or np.asarray(poses).shape != (num_frames, 3):
        raise ValueError(f"{num_frames} frames of boxes, {len(ids)} of ids, poses of shape {np.asarray(poses).shape}")
    boxes = [np.asarray(b, dtype=np.float64).reshape(-1, 5) for b in boxes]
    ids = [np.asarray(i, dtype=np.int64).reshape(-1) for i in ids]
    for t, (b, i) in enumerate(zip(boxes, ids)):
        if len(b) != len(i):
            raise ValueError(f"frame {t}: {len(b)} boxes but {len(i)} ids")
    poses = np.asarray(poses, dtype=np.float64)
    size, k_max = cfg.feature_size, cfg.head.num_queries

    # ---- detection targets: newest frame
    newest = boxes[-1]
    rows, cols, inside = centre_cells(newest[:, :2], cfg)
    if not inside.all():
        log.warning(
            "build_targets: %d of %d newest-frame boxes have their centre outside the %dx%d grid; no target",
            int((~inside).sum()),
            len(newest),
            size,
            size,
        )
    kept = np.flatnonzero(inside)
    heatmap = np.zeros((size, size), np.float64)
    for k in kept:  # every object is a heatmap peak, also those beyond the K box slots (never a negative)
        draw_gaussian(heatmap, int(rows[k]), int(cols[k]), heatmap_radius(newest[k], cfg))
    if len(kept) > k_max:
        log.warning(
            "build_targets: %d objects in the newest frame, K = %d; %d get no box target (still heatmap peaks)",
            len(kept),
            k_max,
            len(kept) - k_max,
        )
        kept = kept[:k_max]
    centre_index = np.zeros(k_max, np.int64)
    box_mask = np.zeros(k_max, np.float32)
    offset = np.zeros((k_max, 2), np.float32)
    log_size = np.zeros((k_max, 2), np.float32)
    rotation = np.zeros((k_max, 2), np.float32)
    box_targets = np.zeros((k_max, 5), np.float32)
    for slot, k in enumerate(kept):
        box, row, col = newest[k], int(rows[k]), int(cols[k])
        centre_index[slot] = row * size + col
        box_mask[slot] = 1.0
        offset[slot] = (
            box[0] / cfg.cell_size + size / 2.0 - (col + 0.5),
            (row + 0.5) - (size / 2.0 - box[1] / cfg.cell_size),
        )
        log_size[slot], rotation[slot] = box_regression_targets(box, cfg)
        box_targets[slot] = box

    # ---- pseudo-GT flow: every consecutive pair
    pairs = [
        _flow_pair(boxes[t - 1], ids[t - 1], poses[t - 1], boxes[t], ids[t], poses[t], cfg)
        for t in range(1, num_frames)
    ]
    empty = np.zeros((0, 1, size, size), np.float32)
    # The newest frame's ignore regions (rafd.data.labels.IGNORE_CLASS): their cells are no heatmap negatives.
    heatmap_weight = np.ones((1, size, size), np.float32)
    if ignore is not None and len(ignore):
        cells = feature_cell_centres(size, cfg.input_size, cfg.resolution).reshape(-1, 2)
        inside = points_in_boxes(cells, ignore).any(axis=1).reshape(size, size)
        heatmap_weight[0][inside & (heatmap < 1.0 - 1e-6)] = 0.0
    return {
        "heatmap": heatmap[None].astype(np.float32),
        "heatmap_weight": heatmap_weight,
        "centre_index": centre_index,
        "box_mask": box_mask,
        "offset": offset,
        "log_size": log_size,
        "rotation": rotation,
        "boxes": box_targets,
        "flow": np.stack([p[0] for p in pairs]) if pairs else np.zeros((0, 2, size, size), np.float32),
        "flow_valid": np.stack([p[1] for p in pairs]) if pairs else empty,
        "flow_foreground": np.stack([p[2] for p in pairs]) if pairs else empty.copy(),
    }
