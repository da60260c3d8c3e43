"""Full-scan evaluation: streaming tiles through the PyTorch model equals running each tile's window."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from rafd.data import RadarWindowDataset
from rafd.eval.fullscan import predict_full_scan, scan_config
from rafd.eval.tiled import TileGrid, detect_windows
from rafd.preprocess import to_model_input


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
    """Per tile, before merging: the streamed caches give what each tile's own window gives (merging is exact but a
    1e-6 change can hand a detection on a core border to the neighbouring tile, so it is compared raw); with warm-up
    windows too, whose old end repeats the sequence's first frame (every frame of a short real sequence is scored)."""
    import rafd.eval.fullscan
    import rafd.eval.tiled
    from rafd.assets import default_checkpoint
    from rafd.model.checkpoint import load_checkpoint

    model, cfg, _ = load_checkpoint(default_checkpoint())  # trained weights: stable scores, as in use
    dataset = RadarWindowDataset(scans, split="test", cfg=scan_config(cfg, _scan_size()), warm_up=warm_up)
    grid = TileGrid.for_model(cfg.input_size, scan_size=_scan_size())
    tiles = grid.per_side**2
    raw: dict[str, list] = {"streamed": [], "windows": []}

    def recording(key):
        def merge(grid, boxes, scores, *args, **kwargs):
            raw[key].append((np.asarray(boxes), np.asarray(scores)))
            return rafd.eval.tiled.Detections(np.zeros((0, 5)), np.zeros(0), np.zeros(0, int))

        return merge

    monkeypatch.setattr(rafd.eval.fullscan, "merge_tiles", recording("streamed"))
    results = predict_full_scan(model, dataset, cfg, grid=grid, progress=False)
    assert len(results) == len(dataset) == (6 if warm_up else 3) and tiles > 4
    # the label-free flow check of each scan's newest pair, over every tile (no flow targets for whole scans)
    for result in results:
        tally = result.flow_tally
        assert tally is not None and tally.pairs == 1 and tally.labelled_pairs == 0
        assert tally.cells.sum() == tiles * cfg.feature_size**2 and np.isfinite(tally.magnitude).all()
    # a warm-up window of the first frame pairs that frame with itself
    tallies = [r.flow_tally for r in results if r.flow_tally is not None]
    assert [t.repeated_pairs for t in tallies] == ([1, 0, 0, 0, 0, 0] if warm_up else [0, 0, 0])
    if not warm_up:  # --max-windows hands a WindowSubset: its windows only, the same figures
        from rafd.data.windows import WindowSubset

        (one,) = predict_full_scan(model, WindowSubset(dataset, [1]), cfg, grid=grid, progress=False)
        assert one.frame == results[1].frame and one.flow_tally is not None
        assert one.flow_tally.cells.sum() == tallies[1].cells.sum()
        np.testing.assert_allclose(one.flow_tally.magnitude, tallies[1].magnitude, rtol=1e-6)
        raw["streamed"].pop()  # (recorded by the merge above; compared below are the full run's)

    def run(crops: np.ndarray, poses: np.ndarray):
        with torch.no_grad():
            out = model(torch.from_numpy(to_model_input(crops))[:, :, None], torch.from_numpy(poses).float())
        return out["boxes"].numpy(), out["scores"].numpy()

    monkeypatch.setattr(rafd.eval.tiled, "merge_tiles", recording("windows"))
    for index, result in enumerate(results):
        window = dataset[index]
        detect_windows(grid, list(window["frames"]), window["poses"], run)
        np.testing.assert_allclose(result.ground_truth, window["boxes"][-1], atol=1e-12)
    for (boxes, scores), (want_boxes, want_scores) in zip(raw["streamed"], raw["windows"]):
        assert boxes.shape == want_boxes.shape == (tiles, cfg.head.num_queries, 5)
        for tile in range(tiles):  # the K candidates as sets: top-K ties may come in another order
            got = np.concatenate([boxes[tile], scores[tile][:, None]], 1)
            want = np.concatenate([want_boxes[tile], want_scores[tile][:, None]], 1)
            confident = got[:, 5] > 0.05  # the tail below may swap at the top-K boundary
            distance = np.abs(got[confident][:, None] - want[None]).max(-1)  # [k, K]
            assert distance.min(1).max() < 1e-3 if confident.any() else True


def test_keep_flow_gives_each_scan_its_tiles_flow_mosaic(scans: Path) -> None:
    """keep_flow: every scan after a stream's first carries one FlowField per tile, on the tile's grid (the crop's
    cells shifted by the tile's offset), with the pair's interval and the flow search's reach."""
    from rafd.assets import default_checkpoint
    from rafd.eval.tracking_inputs import reach_of
    from rafd.model.checkpoint import load_checkpoint

    model, cfg, _ = load_checkpoint(default_checkpoint())
    dataset = RadarWindowDataset(scans, split="test", cfg=scan_config(cfg, _scan_size()), warm_up=True)
    grid = TileGrid.for_model(cfg.input_size, scan_size=_scan_size())
    results = predict_full_scan(model, dataset, cfg, grid=grid, progress=False, keep_flow=True)
    assert results[0].flow_fields is None  # a stream's first scan has no pair
    stamps = dataset.sequences[0].timestamps
    for k, result in enumerate(results[1:], start=1):
        fields = result.flow_fields
        assert fields is not None and len(fields) == grid.per_side**2
        for field, offset in zip(fields, grid.offsets_m):
            height, width = field.grid.shape
            assert field.flow.shape == (2, height, width) and field.validity.shape == (height, width)
            assert np.allclose(field.grid.centres().mean((0, 1)), offset, atol=1e-6)
            assert field.interval_s == pytest.approx(stamps[k] - stamps[k - 1])
            assert field.reach_m == pytest.approx(reach_of(cfg))
