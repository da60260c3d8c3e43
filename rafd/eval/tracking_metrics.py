"""The field's tracking metrics through TrackEval (the HOTA authors' implementation, as MOTChallenge and KITTI run it):
HOTA with DetA and AssA, CLEAR's MOTA and ID switches, Identity's IDF1, on BEV centre distances.

Similarity of a labelled vehicle and a tracked box: s = max(0, 1 - d / (2 * MATCH_DISTANCE_M)), d their centres'
distance in metres, so CLEAR and Identity (threshold s >= 0.5) match within MATCH_DISTANCE_M = 2 m, as nuScenes'
tracking benchmark does; HOTA averages over its thresholds alpha = 0.05 ... 0.95, i.e. over matching distances from
3.8 m down to 0.2 m, and HOTA@2m is its value at alpha = 0.5 (the 2 m match).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rafd.protocol import CENTRE_DISTANCE_M

MATCH_DISTANCE_M = CENTRE_DISTANCE_M  # 2 m


@dataclass(frozen=True)
class FrameTracks:
    """One scan for the metrics: labelled centres [M, 2] with ids [M], tracked centres [N, 2] with track ids [N]."""

    truth_xy: np.ndarray
    truth_ids: np.ndarray
    track_xy: np.ndarray
    track_ids: np.ndarray


def similarity(truth_xy: np.ndarray, track_xy: np.ndarray) -> np.ndarray:
    """[M, 2], [N, 2] -> [M, N] in [0, 1]: 1 - d / (2 * MATCH_DISTANCE_M), clipped at 0 (>= 0.5 within 2 m)."""
    difference = truth_xy[:, None, :] - track_xy[None, :, :]  # [M, N, 2]
    d = np.sqrt((difference**2).sum(-1))  # [M, N]
    return np.clip(1.0 - d / (2.0 * MATCH_DISTANCE_M), 0.0, 1.0)


def trackeval_data(frames: Sequence[FrameTracks]) -> dict[str, Any]:
    """One sequence in TrackEval's per-sequence form (ids renumbered 0..n-1 per sequence, as its datasets do)."""
    truth_ids = np.unique(np.concatenate([f.truth_ids for f in frames] + [np.zeros(0, np.int64)]))
    track_ids = np.unique(np.concatenate([f.track_ids for f in frames] + [np.zeros(0, np.int64)]))
    return {
        "num_timesteps": len(frames),
        "num_gt_ids": len(truth_ids),
        "num_tracker_ids": len(track_ids),
        "num_gt_dets": int(sum(len(f.truth_ids) for f in frames)),
        "num_tracker_dets": int(sum(len(f.track_ids) for f in frames)),
        "gt_ids": [np.searchsorted(truth_ids, f.truth_ids).astype(int) for f in frames],
        "tracker_ids": [np.searchsorted(track_ids, f.track_ids).astype(int) for f in frames],
        "similarity_scores": [similarity(f.truth_xy.reshape(-1, 2), f.track_xy.reshape(-1, 2)) for f in frames],
    }


def tracking_metrics(sequences: Mapping[str, Sequence[FrameTracks]]) -> dict[str, float]:
    """{sequence: its scans in order} -> HOTA, DetA, AssA (alpha-averaged, and @2m), MOTA, MOTP-free counts (TP,
    FN, FP, IDSW), IDF1 with IDP/IDR, pooled over the sequences as TrackEval combines them."""
    from trackeval.metrics import CLEAR, HOTA, Identity

    quiet = {"THRESHOLD": 0.5, "PRINT_CONFIG": False}
    metrics = {"hota": HOTA(), "clear": CLEAR(dict(quiet)), "identity": Identity(dict(quiet))}
    per_sequence: dict[str, dict[str, Any]] = {name: {} for name in metrics}
    with contextlib.redirect_stdout(io.StringIO()):  # TrackEval prints its configs and timings
        for name, frames in sequences.items():
            data = trackeval_data(frames)
            for metric_name, metric in metrics.items():
                per_sequence[metric_name][name] = metric.eval_sequence(data)
        combined = {name: metric.combine_sequences(per_sequence[name]) for name, metric in metrics.items()}
    hota, clear, identity = combined["hota"], combined["clear"], combined["identity"]
    at_2m = int(np.argmin(np.abs(np.arange(0.05, 0.99, 0.05) - 0.5)))  # TrackEval's alphas
    return {
        "HOTA": 100.0 * float(np.mean(hota["HOTA"])),
        "DetA": 100.0 * float(np.mean(hota["DetA"])),
        "AssA": 100.0 * float(np.mean(hota["AssA"])),
        "HOTA@2m": 100.0 * float(hota["HOTA"][at_2m]),
        "DetA@2m": 100.0 * float(hota["DetA"][at_2m]),
        "AssA@2m": 100.0 * float(hota["AssA"][at_2m]),
        "MOTA": 100.0 * float(clear["MOTA"]),
        "IDF1": 100.0 * float(identity["IDF1"]),
        "IDP": 100.0 * float(identity["IDP"]),
        "IDR": 100.0 * float(identity["IDR"]),
        "IDSW": int(clear["IDSW"]),
        "TP": int(clear["CLR_TP"]),
        "FN": int(clear["CLR_FN"]),
        "FP": int(clear["CLR_FP"]),
        "frames": int(sum(len(frames) for frames in sequences.values())),
        "objects": int(sum(len(f.truth_ids) for frames in sequences.values() for f in frames)),
    }
