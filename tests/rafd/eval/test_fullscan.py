"""Full-scan evaluation: the model streamed over a whole scan's tiles (rafd.runtime.view, via the runner's cache) gives
each tile what the model's forward gives on that tile's own padded window."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from export.verify import window_from_history
from rafd.data import RadarWindowDataset
from rafd.eval.fullscan import predict_full_scan, scan_config
from rafd.geometry import relative_pose
from rafd.runtime.view import View


def _scan_size() -> int:
    """2.5 model inputs: 3 x 3 overlapping tiles for any shipped model's input size."""
    from rafd.assets import default_checkpoint
    from rafd.model.checkpoint import read_checkpoint

    return 2 * (5 * read_checkpoint(default_checkpoint())[1].input_size // 4)


@pytest.fixture(scope="module")
def scans(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rafd.sim import simulate_sequence

    root = tmp_path_factory.mktemp("full")
    simulate_sequence(root / "seq", seed=9, num_frames=6, split="test", size=_scan_size())
    return root


@pytest.mark.slow
@pytest.mark.parametrize("warm_up", [False, True])
def test_streamed_tiles_equal_each_tiles_window(scans: Path, monkeypatch: pytest.MonkeyPatch, warm_up: bool) -> None:
    """Per tile, before merging: the stream gives what each tile's own padded window gives through model.forward
    (merging is exact but a 1e-6 change can hand a detection on a core border to the neighbouring tile, so it is
    compared raw); with warm-up windows too, whose old end repeats the sequence's first frame."""
    from rafd.assets import default_checkpoint
    from rafd.model.checkpoint import load_checkpoint

    model, cfg, _ = load_checkpoint(default_checkpoint())  # trained weights: stable scores, as in use
    dataset = RadarWindowDataset(scans, split="test", cfg=scan_config(cfg, _scan_size()), warm_up=warm_up)
    raw: list[tuple[np.ndarray, np.ndarray]] = []
    merge = View.merge

    def recording(self, boxes, scores, *args, **kwargs):
        raw.append((np.asarray(boxes), np.asarray(scores)))
        return merge(self, boxes, scores, *args, **kwargs)

    monkeypatch.setattr(View, "merge", recording)
    results = predict_full_scan(model, dataset, cfg, progress=False)
    view = View.of(_scan_size(), cfg.input_size, cfg.resolution, cfg.input_size // cfg.feature_size)
    tiles = len(view.tiles)
    assert len(results) == len(dataset) == (6 if warm_up else 3) and tiles == 9
    for result in results:  # the label-free flow check of each scan's newest pair, over every tile
        tally = result.flow_tally
        assert tally is not None and tally.pairs == 1 and tally.labelled_pairs == 0
        assert tally.cells.sum() == tiles * cfg.feature_size**2 and np.isfinite(tally.magnitude).all()
    tallies = [r.flow_tally for r in results if r.flow_tally is not None]
    assert [t.repeated_pairs for t in tallies] == ([1, 0, 0, 0, 0, 0] if warm_up else [0, 0, 0])
    sequence = dataset.sequences[0]
    for index, result in enumerate(results):
        newest = result.frame - sequence.numbers[0]  # the window's newest frame's position in the sequence
        history = [dataset._scan(0, k) for k in range(newest + 1)]
        frames = np.stack([view.crops(scan) for scan in history], 1)  # [V, k + 1, S, S]
        poses = np.stack([view.tile_poses(sequence.poses[k]) for k in range(newest + 1)], 1)  # [V, k + 1, 3]
        boxes, scores = raw[index]
        assert boxes.shape == (tiles, cfg.head.num_queries, 5)
        for tile in range(tiles):
            window, window_poses = window_from_history(list(frames[tile]), poses[tile], cfg.num_frames)
            local = relative_pose(window_poses, window_poses[-1])  # in the newest tile frame, as a stream's are
            with torch.no_grad():
                out = model(torch.from_numpy(window)[None, :, None], torch.from_numpy(local).float()[None])
            want = np.concatenate([out["boxes"][0].numpy(), out["scores"][0].numpy()[:, None]], 1)
            got = np.concatenate([boxes[tile], scores[tile][:, None]], 1)
            confident = got[:, 5] > 0.05  # the K candidates as sets; the tail below may swap at the top-K boundary
            distance = np.abs(got[confident][:, None] - want[None]).max(-1)  # [k, K]
            assert distance.min(1).max() < 1e-3 if confident.any() else True, (index, tile)


def test_keep_flow_gives_each_scan_its_tiles_flow_fields(scans: Path) -> None:
    """keep_flow: every scan after a stream's first carries one FlowField per stepped tile, on the tile's grid (the
    crop's cells shifted by the tile's offset), with the pair's interval and the flow search's reach."""
    from rafd.assets import default_checkpoint
    from rafd.eval.tracking_inputs import reach_of
    from rafd.model.checkpoint import load_checkpoint

    model, cfg, _ = load_checkpoint(default_checkpoint())
    dataset = RadarWindowDataset(scans, split="test", cfg=scan_config(cfg, _scan_size()), warm_up=True)
    view = View.of(_scan_size(), cfg.input_size, cfg.resolution, cfg.input_size // cfg.feature_size)
    results = predict_full_scan(model, dataset, cfg, progress=False, keep_flow=True)
    assert results[0].flow_fields is None  # a stream's first scan has no pair
    stamps = dataset.sequences[0].timestamps
    for k, result in enumerate(results[1:], start=1):
        fields = result.flow_fields
        assert fields is not None and len(fields) == len(view.tiles)
        for field, offset in zip(fields, view.offsets_m):
            height, width = field.grid.shape
            assert field.flow.shape == (2, height, width) and field.validity.shape == (height, width)
            assert np.allclose(field.grid.centres().mean((0, 1)), offset, atol=1e-6)
            assert field.interval_s == pytest.approx(stamps[k] - stamps[k - 1])
            assert field.reach_m == pytest.approx(reach_of(cfg))
