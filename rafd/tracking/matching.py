"""Association of detections with predicted tracks: gated centre distances, then a global (Hungarian, AB3DMOT) or
closest-first (greedy, CenterPoint) assignment."""

from __future__ import annotations

import numpy as np

UNMATCHABLE = 1e9  # the cost of a pair outside a gate (never chosen: the pairs above the gate are dropped after)


def gated_costs(
    predicted: np.ndarray,
    detections: np.ndarray,
    mahalanobis_sq: np.ndarray,
    gates_m: np.ndarray,
    sigmas: float,
    same_class: np.ndarray,
) -> np.ndarray:
    """Predicted centres [T, 2], detection centres [D, 2], squared Mahalanobis distances [T, D], Euclidean gates
    [T] metres, the Mahalanobis gate in sigmas and class agreement [T, D] -> costs [T, D] (metres; UNMATCHABLE
    outside a gate)."""
    difference = detections[None, :, :] - predicted[:, None, :]  # [T, D, 2]
    distance = np.sqrt((difference * difference).sum(-1))  # [T, D]
    allowed = (distance <= gates_m[:, None]) & (mahalanobis_sq <= sigmas**2) & same_class
    return np.where(allowed, distance, UNMATCHABLE)


def assign(costs: np.ndarray, how: str) -> tuple[np.ndarray, np.ndarray]:
    """Costs [T, D] -> (track rows [M], detection columns [M]) of the pairs kept, every pair within its gates."""
    if costs.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if how == "greedy":
        rows, columns = _greedy(costs)
    else:
        # imported here: greedy matching runs where scipy (~140 MB installed) is not
        from scipy.optimize import linear_sum_assignment

        rows, columns = linear_sum_assignment(costs)
    keep = costs[rows, columns] < UNMATCHABLE
    return np.asarray(rows, np.int64)[keep], np.asarray(columns, np.int64)[keep]


def _greedy(costs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest pair first, each track and detection used once (CenterPoint's greedy_assignment)."""
    order = np.argsort(costs, axis=None, kind="stable")
    used_rows, used_columns = np.zeros(costs.shape[0], bool), np.zeros(costs.shape[1], bool)
    rows, columns = [], []
    for flat in order:
        row, column = divmod(int(flat), costs.shape[1])
        if costs[row, column] >= UNMATCHABLE:
            break
        if used_rows[row] or used_columns[column]:
            continue
        used_rows[row] = used_columns[column] = True
        rows.append(row)
        columns.append(column)
    return np.array(rows, np.int64), np.array(columns, np.int64)
