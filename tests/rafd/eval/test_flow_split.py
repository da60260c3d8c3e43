"""rafd.eval.flow_split: flow EPE on vehicles, on the static background and by ring from the crop's edge; the
label-free check; the vehicle EPE stays the figure rafd eval always reported."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rafd.eval.flow_split import (
    RING_NAMES,
    FlowTally,
    flow_report,
    pooled,
    ring_map,
    tally_pair,
)
from rafd.eval.predict import FrameResult, _epe, summarise
from rafd.eval.run import flow_figures, jsonable
from rafd.eval.table import format_flow_table
from rafd.flow_validity import flow_validity, search_reach_m

H = 32  # cells a side


def ring_cells(k: int) -> int:
    return 4 * (H - 2 * k - 1)  # cells of ring k of an H x H grid


def edge_flow(edge_m: float = 1.0, interior_m: float = 0.0) -> np.ndarray:
    """[2, H, H]: edge_m along x on ring 0, interior_m on rings 8+, 0 between."""
    flow = np.zeros((2, H, H))
    rings = ring_map(H, H)
    flow[0][rings == 0] = edge_m
    flow[0][rings == 8] = interior_m
    return flow


def identity_validity(stride: int = 4) -> np.ndarray:
    """Validity at rest on a grid of 4 px cells at 1 m per pixel (global matching on the detection grid)."""
    return flow_validity(np.zeros(3), H, 4 * H, 1.0, stride, search_reach_m(stride, 1.0, 0))


def test_rings_count_cells_from_the_nearest_edge_capped_at_the_interior():
    rings = ring_map(H, H)
    assert rings[0, 5] == rings[5, 0] == rings[H - 1, 9] == 0 and rings[1, 1] == 1 and rings[7, 20] == 7
    assert rings[H // 2, H // 2] == 8 and rings.max() == 8
    for k in range(8):
        assert (rings == k).sum() == ring_cells(k)
    assert RING_NAMES == ("0", "1", "2", "3", "4", "5", "6", "7", "8+")


def test_a_flow_of_one_metre_at_the_edge_and_zero_inside_gives_ring_0_epe_1():
    everywhere = np.ones((H, H))
    tally = tally_pair(edge_flow(1.0), np.ones((H, H)), np.zeros((2, H, H)), everywhere, np.zeros((H, H)))
    report = flow_report(tally)
    assert report["background_epe_by_ring"] == pytest.approx([1.0] + [0.0] * 8)
    assert report["background_cells_by_ring"][:8] == [ring_cells(k) for k in range(8)]
    assert report["background_epe"] == pytest.approx(ring_cells(0) / H**2)
    assert report["edge_ratio"] == math.inf  # an interior of 0: any edge flow is infinitely larger
    assert jsonable(report)["edge_ratio"] is None  # standard JSON
    assert report["label_free"]["magnitude_by_ring"] == pytest.approx([1.0] + [0.0] * 8)
    assert math.isnan(report["vehicle_epe"]) and report["vehicle_cells"] == 0


def test_the_edge_ratio_is_rings_0_and_1_over_the_interior():
    everywhere = np.ones((H, H))
    flow = edge_flow(1.0, 0.1)
    tally = tally_pair(flow, np.ones((H, H)), np.zeros((2, H, H)), everywhere, np.zeros((H, H)))
    report = flow_report(tally)
    edge_mean = ring_cells(0) * 1.0 / (ring_cells(0) + ring_cells(1))  # ring 1 is 0
    assert report["background_epe_by_ring"][8] == pytest.approx(0.1)
    assert report["edge_ratio"] == pytest.approx(edge_mean / 0.1)
    assert report["label_free"]["edge_ratio"] == pytest.approx(edge_mean / 0.1)


def test_vehicle_cells_are_foreground_background_is_the_rest_with_a_target():
    flow = edge_flow(1.0, 0.1)
    gt = np.zeros((2, H, H))
    foreground = np.zeros((H, H))
    foreground[14:18, 14:18] = 1.0  # a vehicle in the interior, moving 0.5 m forward
    gt[1][foreground > 0] = 0.5
    target = np.ones((H, H))
    target[20:22, 20:22] = 0.0  # a vehicle new in this frame: no target at all
    report = flow_report(tally_pair(flow, np.ones((H, H)), gt, target, foreground))
    assert report["vehicle_cells"] == 16
    assert report["vehicle_epe"] == pytest.approx(math.hypot(0.1, 0.5))
    assert report["background_cells"] == H * H - 16 - 4
    assert report["background_cells_by_ring"][8] == (H - 16) ** 2 - 16 - 4
    assert report["background_epe_by_ring"][8] == pytest.approx(0.1)


def test_the_valid_split_drops_the_cells_below_the_validity_threshold():
    everywhere = np.ones((H, H))
    validity = identity_validity()  # ring 0 invalid, the rest valid
    tally = tally_pair(edge_flow(1.0, 0.1), validity, np.zeros((2, H, H)), everywhere, np.zeros((H, H)))
    report = flow_report(tally)
    assert report["background_cells_by_ring_valid"][0] == 0 and math.isnan(report["background_epe_by_ring_valid"][0])
    assert report["background_cells_by_ring_valid"][1:8] == [ring_cells(k) for k in range(1, 8)]
    assert report["edge_rings_valid"] == [1, 2]  # the outermost rings holding valid cells
    assert report["edge_ratio_valid"] == pytest.approx(0.0)  # the valid cells next to the edge are still
    assert report["background_epe_valid"] == pytest.approx(0.1 * (H - 16) ** 2 / (H - 2) ** 2)
    assert report["label_free"]["edge_ratio_valid"] == pytest.approx(0.0)


def test_without_flow_targets_only_the_label_free_check_is_reported():
    tally = tally_pair(edge_flow(1.0, 0.1), identity_validity())
    report = flow_report(tally, mode="full_scan_tiles")
    assert report["pairs"] == 1 and report["labelled_pairs"] == 0 and "background_epe" not in report
    free = report["label_free"]
    assert free["magnitude_by_ring"] == pytest.approx([1.0] + [0.0] * 7 + [0.1])
    assert free["cells_by_ring"] == [ring_cells(k) for k in range(8)] + [(H - 16) ** 2]
    text = format_flow_table(report)
    assert "each tile's own edge" in text and "no flow targets" in text and "EPE" not in text
    assert "|flow|, all cells (no labels)" in text and "nan" not in text


def test_tallies_pool_cell_weighted_and_count_repeated_pairs():
    first = tally_pair(edge_flow(1.0, 0.1), identity_validity())
    second = tally_pair(np.zeros((2, H, H)), identity_validity(), repeated=True)
    both = pooled([first, None, second])
    assert both.pairs == 2 and both.repeated_pairs == 1 and both.labelled_pairs == 0
    free = flow_report(both)["label_free"]
    assert free["magnitude_by_ring"][0] == pytest.approx(0.5) and free["magnitude_by_ring"][8] == pytest.approx(0.05)
    assert "pair a frame with itself" in format_flow_table(flow_report(both))
    assert flow_report(FlowTally())["pairs"] == 0
    assert "no flow" in format_flow_table(flow_report(FlowTally()))


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="NaN"):
        tally_pair(np.full((2, H, H), np.nan), np.ones((H, H)))
    with pytest.raises(ValueError, match="validity"):
        tally_pair(np.zeros((2, H, H)), np.ones((H - 1, H)))


def frame_result(rng: np.random.Generator) -> FrameResult:
    """A frame as rafd.eval.predict builds it, EPE by the old computation (_epe) and the tally alongside."""
    pred, gt = rng.normal(0, 0.3, (2, 2, H, H))
    foreground = np.zeros((H, H))
    top, left = rng.integers(0, H - 6, 2)
    foreground[top : top + 6, left : left + 6] = 1.0
    target = np.ones((H, H))
    target[rng.integers(0, H, 5), rng.integers(0, H, 5)] = 0.0
    epe_all, cells_all = _epe(pred, gt, target > 0)
    epe_fg, cells_fg = _epe(pred, gt, (foreground > 0) & (target > 0))
    return FrameResult(
        sequence="a",
        frame=1,
        predictions=np.zeros((0, 6)),
        ground_truth=np.zeros((0, 5)),
        epe_all=epe_all,
        epe_foreground=epe_fg,
        cells_all=cells_all,
        cells_foreground=cells_fg,
        flow_tally=tally_pair(pred, identity_validity(), gt, target, foreground),
    )


def test_vehicle_epe_is_exactly_the_epe_foreground_rafd_eval_always_reported():
    rng = np.random.default_rng(3)
    results = [frame_result(rng) for _ in range(5)]
    overall = summarise(results)
    flow = flow_figures(results, overall, full_scan=False)
    assert flow["vehicle_epe"] == overall["epe_foreground"]  # the very number, not a recomputation
    assert flow["vehicle_cells"] == sum(r.cells_foreground for r in results)
    # the tally's own vehicle sums agree with the old computation
    assert flow_report(pooled(r.flow_tally for r in results))["vehicle_epe"] == pytest.approx(
        overall["epe_foreground"], rel=1e-12
    )
    # vehicle + background = every cell with a target: epe_all
    cells = flow["vehicle_cells"] + flow["background_cells"]
    assert cells == sum(r.cells_all for r in results)
    pooled_all = (
        flow["vehicle_epe"] * flow["vehicle_cells"] + flow["background_epe"] * flow["background_cells"]
    ) / cells
    assert pooled_all == pytest.approx(overall["epe_all"], rel=1e-12)
