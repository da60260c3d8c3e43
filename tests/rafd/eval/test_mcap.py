"""rafd.eval.mcap: an evaluated window's logged frame carries flow arrows only where the flow is valid."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="MCAP logs need the logs extra (foxglove-sdk)")

from rafd.config import RaFDConfig  # noqa: E402
from rafd.eval.mcap import evaluation_frame  # noqa: E402
from rafd.eval.predict import FrameResult  # noqa: E402


def test_logged_flow_skips_the_cells_below_the_validity_threshold():
    cfg = RaFDConfig()
    size, cells = cfg.input_size, cfg.feature_size
    flow = np.zeros((2, cells, cells))
    flow[0] = 1.0  # everything moves 1 m: the edge rings included
    result = FrameResult("s", 3, np.zeros((0, 6)), np.zeros((0, 5)), np.nan, np.nan, 0, 0, flow=flow)
    window = {
        "frames": np.zeros((cfg.num_frames, size, size), np.uint8),
        "poses": np.zeros((cfg.num_frames, 3)),  # at rest: only the outer rings are invalid
        "timestamps": np.arange(cfg.num_frames, dtype=np.float64),
    }
    logged = evaluation_frame(window, result, cfg)
    assert logged.flow_heads is not None and 0 < len(logged.flow_heads) < cells * cells
    edge = 0.5 * size * cfg.resolution - cfg.cell_size  # centres of ring 0 lie half a cell inside this
    assert np.abs(logged.flow_heads).max() < edge  # no arrow on the outermost ring
