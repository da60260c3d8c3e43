"""Where the flow is right: EPE on vehicles, on the static background, and by ring from the crop's edge (torch-free).

The flow of a cell near the crop's edge is measured over a shorter reach than in the interior (rafd.flow_validity);
on a static scene such a border shows as large flow where the true flow is 0. These tallies make that visible:
- rings: ring k holds the detection-grid cells k cells from the nearest edge of the crop (ring 0 the outermost),
  rings 0..7, then "8+" for the interior (ring_map);
- vehicle cells: the targets' flow_foreground (matched vehicles' regions; the EPE rafd eval has always reported as
  epe_foreground); background cells: flow_valid and not flow_foreground (every other cell with a target, whose
  true flow is 0 after ego removal: rafd.data.targets);
- the same split restricted to the cells whose validity (rafd.flow_validity) reaches FLOW_VALID_MIN;
- a label-free check: the mean flow magnitude by ring over all cells (a scene is mostly static once ego motion is
  removed), for real scans without flow targets;
- edge ratio: the figure of rings 0-1 over that of the interior (8+); 1 means no border artefact. Validity removes
  the outermost rings altogether, so the valid variants' edge ratio uses the two outermost rings that hold valid
  cells (edge_rings_valid, from the label-free cell counts: one choice for every valid row).
Tallies are sums and counts, so pairs, batches and tiles pool by addition (every cell weighs the same).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from rafd.flow_validity import FLOW_VALID_MIN

RING_COUNT = 9  # rings 0..7 from the crop's edge, then the interior 8+
RING_NAMES = tuple(str(k) for k in range(RING_COUNT - 1)) + (f"{RING_COUNT - 1}+",)
EDGE_RINGS = (0, 1)  # the edge ratio's numerator ...
INTERIOR = RING_COUNT - 1  # ... over the interior's figure


def ring_map(height: int, width: int) -> np.ndarray:
    """[H, W] int: each cell's distance in cells to the nearest edge of the grid, capped at RING_COUNT - 1."""
    rows = np.minimum(np.arange(height), height - 1 - np.arange(height))
    cols = np.minimum(np.arange(width), width - 1 - np.arange(width))
    return np.minimum(np.minimum(rows[:, None], cols[None, :]), RING_COUNT - 1).astype(np.int64)


def _zeros() -> np.ndarray:
    return np.zeros(RING_COUNT, np.float64)


@dataclass
class FlowTally:
    """Sums ([RING_COUNT] per ring) of one or more newest pairs; `_cells` count the cells behind each sum."""

    vehicle_error: np.ndarray = field(default_factory=_zeros)
    vehicle_cells: np.ndarray = field(default_factory=_zeros)
    vehicle_error_valid: np.ndarray = field(default_factory=_zeros)
    vehicle_cells_valid: np.ndarray = field(default_factory=_zeros)
    background_error: np.ndarray = field(default_factory=_zeros)
    background_cells: np.ndarray = field(default_factory=_zeros)
    background_error_valid: np.ndarray = field(default_factory=_zeros)
    background_cells_valid: np.ndarray = field(default_factory=_zeros)
    magnitude: np.ndarray = field(default_factory=_zeros)  # label-free: |flow| over all cells
    cells: np.ndarray = field(default_factory=_zeros)
    magnitude_valid: np.ndarray = field(default_factory=_zeros)
    cells_valid: np.ndarray = field(default_factory=_zeros)
    pairs: int = 0
    labelled_pairs: int = 0  # pairs with flow targets
    repeated_pairs: int = 0  # pairs of a frame with itself (a warm-up window's padding, --past-as-newest)

    def __add__(self, other: FlowTally) -> FlowTally:
        return FlowTally(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})


def _by_ring(values: np.ndarray, mask: np.ndarray, rings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-ring (sum of values, number of cells) under a [H, W] bool mask."""
    chosen = rings[mask]
    return (
        np.bincount(chosen, weights=values[mask], minlength=RING_COUNT).astype(np.float64),
        np.bincount(chosen, minlength=RING_COUNT).astype(np.float64),
    )


def tally_pair(
    flow: np.ndarray,
    validity: np.ndarray,
    gt_flow: np.ndarray | None = None,
    target_valid: np.ndarray | None = None,
    foreground: np.ndarray | None = None,
    repeated: bool = False,
    valid_min: float = FLOW_VALID_MIN,
) -> FlowTally:
    """One pair's predicted flow [2, H, W] (metres) and validity [H, W] -> its FlowTally. With the targets (gt_flow
    [2, H, W], target_valid and foreground [H, W], rafd.data.targets' flow, flow_valid and flow_foreground) the
    EPE split too; without them (real scans) only the label-free magnitudes."""
    pred = np.asarray(flow, dtype=np.float64)
    if pred.ndim != 3 or pred.shape[0] != 2:
        raise ValueError(f"flow must be [2, H, W], got {pred.shape}")
    if not np.all(np.isfinite(pred)):
        raise ValueError("the predicted flow holds NaN/inf")
    rings = ring_map(pred.shape[1], pred.shape[2])
    valid = np.asarray(validity) >= valid_min
    if valid.shape != rings.shape:
        raise ValueError(f"validity of shape {valid.shape} for a flow of {pred.shape}")
    everywhere = np.ones(rings.shape, bool)
    magnitude = np.hypot(pred[0], pred[1])
    tally = FlowTally(pairs=1, repeated_pairs=int(repeated))
    tally.magnitude, tally.cells = _by_ring(magnitude, everywhere, rings)
    tally.magnitude_valid, tally.cells_valid = _by_ring(magnitude, valid, rings)
    if gt_flow is None or target_valid is None or foreground is None:
        return tally
    gt = np.asarray(gt_flow, dtype=np.float64)
    if gt.shape != pred.shape:
        raise ValueError(f"gt_flow shape {gt.shape} differs from the flow's {pred.shape}")
    error = np.linalg.norm(pred - gt, axis=0)  # [H, W], as rafd.eval.metrics.end_point_error
    has_target = np.asarray(target_valid) > 0
    vehicle = has_target & (np.asarray(foreground) > 0)
    background = has_target & ~vehicle
    if not np.all(np.isfinite(error[has_target])):
        raise ValueError("gt_flow holds NaN/inf inside the evaluated region")
    tally.labelled_pairs = 1
    tally.vehicle_error, tally.vehicle_cells = _by_ring(error, vehicle, rings)
    tally.vehicle_error_valid, tally.vehicle_cells_valid = _by_ring(error, vehicle & valid, rings)
    tally.background_error, tally.background_cells = _by_ring(error, background, rings)
    tally.background_error_valid, tally.background_cells_valid = _by_ring(error, background & valid, rings)
    return tally


def pooled(tallies: Iterable[FlowTally | None]) -> FlowTally:
    """The sum of the tallies given (None: a frame without flow)."""
    total = FlowTally()
    for tally in tallies:
        if tally is not None:
            total = total + tally
    return total


def _mean(total: float, cells: float) -> float:
    return float(total / cells) if cells else math.nan


def _ratio(sums: np.ndarray, cells: np.ndarray, edge: Sequence[int]) -> float:
    """Mean over the `edge` rings / mean over the interior; nan when either has no cell (or both are 0), inf when
    only the interior's is 0."""
    edge_mean = _mean(float(sums[list(edge)].sum()), float(cells[list(edge)].sum()))
    interior = _mean(float(sums[INTERIOR]), float(cells[INTERIOR]))
    if not (math.isfinite(edge_mean) and math.isfinite(interior)):
        return math.nan
    if interior == 0:
        return math.inf if edge_mean > 0 else math.nan
    return edge_mean / interior


def _means(sums: np.ndarray, cells: np.ndarray) -> list[float]:
    return [_mean(float(s), float(c)) for s, c in zip(sums, cells)]


def valid_edge_rings(tally: FlowTally) -> list[int]:
    """The two outermost rings (below the interior) holding valid cells: the valid variants' edge rings."""
    return [k for k in range(INTERIOR) if tally.cells_valid[k] > 0][: len(EDGE_RINGS)]


def flow_report(
    tally: FlowTally, vehicle_epe: float | None = None, mode: str = "crop", valid_min: float = FLOW_VALID_MIN
) -> dict[str, Any]:
    """A pooled FlowTally -> report["flow"] (module docstring). `vehicle_epe`: the EPE rafd eval has always
    reported on vehicle cells (summary's epe_foreground), kept as that very number; None: from the tally."""
    edge_valid = valid_edge_rings(tally)
    report: dict[str, Any] = {
        "mode": mode,
        "rings": list(RING_NAMES),
        "flow_valid_min": valid_min,
        "pairs": tally.pairs,
        "labelled_pairs": tally.labelled_pairs,
        "repeated_pairs": tally.repeated_pairs,
        "edge_rings": list(EDGE_RINGS),
        "edge_rings_valid": edge_valid,
    }
    if tally.labelled_pairs:
        report |= {
            "vehicle_epe": _mean(tally.vehicle_error.sum(), tally.vehicle_cells.sum())
            if vehicle_epe is None
            else vehicle_epe,
            "vehicle_cells": int(tally.vehicle_cells.sum()),
            "background_epe": _mean(tally.background_error.sum(), tally.background_cells.sum()),
            "background_cells": int(tally.background_cells.sum()),
            "background_epe_by_ring": _means(tally.background_error, tally.background_cells),
            "background_cells_by_ring": [int(c) for c in tally.background_cells],
            "edge_ratio": _ratio(tally.background_error, tally.background_cells, EDGE_RINGS),
            "vehicle_epe_valid": _mean(tally.vehicle_error_valid.sum(), tally.vehicle_cells_valid.sum()),
            "vehicle_cells_valid": int(tally.vehicle_cells_valid.sum()),
            "background_epe_valid": _mean(tally.background_error_valid.sum(), tally.background_cells_valid.sum()),
            "background_cells_valid": int(tally.background_cells_valid.sum()),
            "background_epe_by_ring_valid": _means(tally.background_error_valid, tally.background_cells_valid),
            "background_cells_by_ring_valid": [int(c) for c in tally.background_cells_valid],
            "edge_ratio_valid": _ratio(tally.background_error_valid, tally.background_cells_valid, edge_valid)
            if len(edge_valid) == len(EDGE_RINGS)
            else math.nan,
        }
    if tally.pairs:
        report["label_free"] = {
            "magnitude": _mean(tally.magnitude.sum(), tally.cells.sum()),
            "magnitude_by_ring": _means(tally.magnitude, tally.cells),
            "cells_by_ring": [int(c) for c in tally.cells],
            "edge_ratio": _ratio(tally.magnitude, tally.cells, EDGE_RINGS),
            "magnitude_valid": _mean(tally.magnitude_valid.sum(), tally.cells_valid.sum()),
            "magnitude_by_ring_valid": _means(tally.magnitude_valid, tally.cells_valid),
            "cells_by_ring_valid": [int(c) for c in tally.cells_valid],
            "edge_ratio_valid": _ratio(tally.magnitude_valid, tally.cells_valid, edge_valid)
            if len(edge_valid) == len(EDGE_RINGS)
            else math.nan,
        }
    return report
