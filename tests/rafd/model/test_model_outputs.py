"""Output contract of RaFD.forward: keys, shapes, dtypes, value ranges."""

from __future__ import annotations

import math

import pytest
import torch

from rafd.model import RaFD, build_model
from rafd.model.boxes import decode_boxes
from rafd.model.head import force_ground_truth, peak_indices


@pytest.mark.parametrize("num_frames", [1, 2, 4])
@pytest.mark.parametrize("batch", [1, 3])
def test_output_keys_shapes_and_dtypes(make_config, make_inputs, num_frames: int, batch: int) -> None:
    cfg = make_config(num_frames)
    model = build_model(cfg).eval()
    assert isinstance(model, RaFD)
    frames, poses = make_inputs(cfg, batch)
    with torch.no_grad():
        out = model(frames, poses)
    hf, k = cfg.feature_size, cfg.head.num_queries
    expected = {
        "heatmap": (batch, 1, hf, hf),
        "scores": (batch, k),
        "boxes": (batch, k, 5),
        "query_indices": (batch, k),
        "pred_offset": (batch, k, 2),
        "pred_log_size": (batch, k, 2),
        "pred_rotation": (batch, k, 2),
    }
    if num_frames > 1:
        expected["flow"] = (batch, num_frames - 1, 2, hf, hf)
    assert {name: tuple(v.shape) for name, v in out.items()} == expected
    assert out["query_indices"].dtype == torch.int64
    for name, value in out.items():
        if name != "query_indices":
            assert value.dtype == torch.float32, name
            assert torch.isfinite(value).all(), name
    assert ((out["scores"] >= 0) & (out["scores"] <= 1)).all()
    assert ((out["query_indices"] >= 0) & (out["query_indices"] < hf * hf)).all()
    # scores are the heatmap at the query cells
    logits = out["heatmap"].flatten(1)
    torch.testing.assert_close(out["scores"], torch.sigmoid(torch.gather(logits, 1, out["query_indices"])))


def test_single_frame_model_has_no_flow_branch(make_config) -> None:
    model = build_model(make_config(1))
    assert model.flow is None and model.propagation is None
    assert not any("flow" in name or "propagation" in name for name, _ in model.named_parameters())


def test_peaks_are_local_maxima_and_gt_slots_are_forced() -> None:
    heatmap = torch.full((1, 1, 8, 8), -5.0)
    heatmap[0, 0, 2, 3] = 3.0
    heatmap[0, 0, 2, 4] = 2.0  # neighbour of a higher peak: suppressed by the 3x3 NMS
    heatmap[0, 0, 6, 6] = 1.0
    peaks = peak_indices(heatmap, 3)
    assert peaks[0, :2].tolist() == [2 * 8 + 3, 6 * 8 + 6]
    assert 2 * 8 + 4 not in peaks[0].tolist()
    gt = torch.tensor([[10, 20, 30]])
    mask = torch.tensor([[1.0, 0.0, 1.0]])
    assert force_ground_truth(peaks, gt, mask)[0].tolist() == [10, peaks[0, 1].item(), 30]
    # fewer GT slots than queries: the rest stay peaks
    assert force_ground_truth(peaks, gt[:, :1], mask[:, :1])[0].tolist() == [10] + peaks[0, 1:].tolist()


def test_gt_indices_drive_the_query_slots(make_config, make_inputs) -> None:
    cfg = make_config(2)
    model = build_model(cfg)
    frames, poses = make_inputs(cfg, 2)
    k = cfg.head.num_queries
    gt = torch.randint(0, cfg.feature_size**2, (2, k))
    mask = torch.zeros(2, k)
    mask[0, :3] = 1
    mask[1, 5] = 1
    out = model(frames, poses, gt_indices=gt, gt_mask=mask)
    chosen = out["query_indices"]
    assert chosen[0, :3].tolist() == gt[0, :3].tolist() and chosen[1, 5] == gt[1, 5]


@pytest.mark.parametrize("encoding, angle", [("as_labelled", 0.7), ("symmetric", 1.4)])
def test_box_decoding(encoding: str, angle: float) -> None:
    centres = torch.tensor([[[1.0, 2.0]]])
    offset = torch.tensor([[[0.5, -0.25]]])  # cells, x right, y forward
    log_size = torch.log(torch.tensor([[[2.0, 4.5]]]))
    rotation = torch.tensor([[[math.sin(angle), math.cos(angle)]]])  # (sin 2yaw, cos 2yaw) when symmetric
    box = decode_boxes(centres, offset, log_size, rotation, cell_size=0.5, encoding=encoding)[0, 0]
    torch.testing.assert_close(box, torch.tensor([1.25, 1.875, 2.0, 4.5, 0.7]))


def test_float64_poses_and_lazy_top_level_import(make_config, make_inputs) -> None:
    import rafd

    cfg = make_config(2)
    model = rafd.build_model(cfg).eval()
    frames, poses = make_inputs(cfg, 1)
    with torch.no_grad():
        single, double = model(frames, poses), model(frames, poses.double())
    for name in single:
        assert single[name].dtype == double[name].dtype
        torch.testing.assert_close(single[name], double[name], atol=1e-4, rtol=1e-4)
