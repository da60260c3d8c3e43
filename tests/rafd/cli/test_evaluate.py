"""rafd-eval: metrics JSON (overall + per sequence) and plots; clear errors on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.cli.evaluate import main


def test_writes_metrics_json_and_plots(trained_checkpoint: Path, sim_root: Path, tmp_path: Path) -> None:
    out_json, plots, detections = tmp_path / "metrics.json", tmp_path / "plots", tmp_path / "dets.npz"
    code = main(
        [
            str(trained_checkpoint),
            str(sim_root),
            "--split",
            "train",
            "--json",
            str(out_json),
            "--plots",
            str(plots),
            "--examples",
            "2",
            "--device",
            "cpu",
            "--quiet",
            "--detections",
            str(detections),
        ]
    )
    assert code == 0
    report = json.loads(out_json.read_text())
    overall = report["overall"]
    for key in ("mAP@0.3", "mAP@0.5", "mAP@0.7"):
        assert 0.0 <= overall[key] <= 100.0
    assert overall["epe_all"] is not None and overall["epe_all"] >= 0.0
    # the flow split (rafd.eval.flow_split): vehicle EPE is the epe_foreground it always was
    flow = report["flow"]
    assert flow["mode"] == "crop" and flow["pairs"] == flow["labelled_pairs"] == overall["frames"]
    assert flow["vehicle_epe"] == overall["epe_foreground"]
    assert len(flow["background_epe_by_ring"]) == len(flow["label_free"]["magnitude_by_ring"]) == 9
    assert flow["background_cells_by_ring_valid"][0] == 0  # the outermost ring is never measured
    assert "edge_ratio" in flow and "edge_ratio_valid" in flow["label_free"]
    assert set(report["per_sequence"]) == {"sim_12_0", "sim_12_1"}
    assert sum(s["frames"] for s in report["per_sequence"].values()) == overall["frames"] > 0
    # the simulated drives' meta.json name their weather: the figures are pooled per condition too
    assert report["per_condition"] and sum(c["frames"] for c in report["per_condition"].values()) == overall["frames"]
    # the saved detections give back the same figures (what rafd bench accuracy compare starts from)
    from rafd.eval.compare import _Scored, load_detections

    frames = load_detections(detections)
    assert len(frames) == overall["frames"] and report["detections"] == str(detections)
    again = _Scored(frames).metrics(np.ones(len(frames)))
    for key in ("mAP@0.3", "mAP@0.5", "mAP@0.7", "centre_AP", "recall_at_1fp"):
        assert again[key] == pytest.approx(overall[key], abs=1e-9)
    pngs = sorted(plots.glob("*.png"))
    assert plots / "precision_recall.png" in pngs
    examples = [p for p in pngs if p.name.startswith("example_")]
    assert len(examples) == 2
    image = cv2.imread(str(examples[0]))
    assert image is not None and image.ndim == 3


def test_bad_split_and_missing_checkpoint_fail_clearly(
    trained_checkpoint: Path, sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(trained_checkpoint), str(sim_root), "--split", "nope", "--device", "cpu"]) != 0
    assert "nope" in capsys.readouterr().err
    assert main([str(tmp_path / "none.pt"), str(sim_root), "--split", "train"]) != 0
    assert "none.pt" in capsys.readouterr().err


def test_calibrate_writes_the_operating_threshold_into_a_copy_of_the_checkpoint(
    trained_checkpoint: Path, sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    import numpy as np

    from rafd.model.checkpoint import read_checkpoint

    checkpoint = Path(shutil.copy(trained_checkpoint, tmp_path / "model.pt"))
    before, cfg_before, _ = read_checkpoint(checkpoint)
    out_json = tmp_path / "metrics.json"
    code = main(
        [
            str(checkpoint),
            str(sim_root),
            "--split",
            "train",
            "--calibrate",
            "2",
            "--json",
            str(out_json),
            "--device",
            "cpu",
            "--quiet",
            "--max-windows",
            "6",
        ]
    )
    assert code == 0, capsys.readouterr().err
    after, cfg_after, meta = read_checkpoint(checkpoint)
    threshold = meta["operating_threshold"]
    assert 0.0 < threshold <= 1.0 and meta["operating_point"]["fp_per_frame_budget"] == 2.0
    assert cfg_after == cfg_before and all(np.array_equal(before[k], after[k]) for k in before)  # weights untouched
    overall = json.loads(out_json.read_text())["overall"]
    # the chosen threshold is the one the report scores at, and it keeps within the budget
    assert overall["score_threshold"] == threshold and overall["fp_per_frame_at_threshold"] <= 2.0
    # a later evaluation uses it by default
    assert (
        main(
            [
                str(checkpoint),
                str(sim_root),
                "--split",
                "train",
                "--json",
                str(out_json),
                "--device",
                "cpu",
                "--quiet",
                "--max-windows",
                "6",
            ]
        )
        == 0
    )
    assert json.loads(out_json.read_text())["overall"]["score_threshold"] == threshold


def test_calibrate_refuses_a_budget_that_is_not_positive(
    trained_checkpoint: Path, sim_root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([str(trained_checkpoint), str(sim_root), "--split", "train", "--calibrate", "0"]) == 2
    assert "--calibrate" in capsys.readouterr().err


def test_like_frames_scores_only_the_frames_a_longer_model_scores(
    trained_checkpoint: Path, sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The 2-frame model scores 4 of each 5-frame drive's frames; --like-frames 4 keeps the 2 a 4-frame model scores."""
    base = [str(trained_checkpoint), str(sim_root), "--split", "train", "--device", "cpu", "--quiet"]
    assert main(base + ["--json", str(tmp_path / "all.json")]) == 0
    assert main(base + ["--like-frames", "4", "--json", str(tmp_path / "like4.json")]) == 0
    every, like4 = (json.loads((tmp_path / name).read_text()) for name in ("all.json", "like4.json"))
    assert every["overall"]["frames"] == 2 * 4 and like4["overall"]["frames"] == 2 * 2
    assert like4["like_frames"] == 4
    assert main(base + ["--like-frames", "6"]) != 0  # 5-frame drives: no frame has 5 predecessors
    assert "predecessors" in capsys.readouterr().err
    assert main(base + ["--like-frames", "0"]) != 0
    assert "--like-frames" in capsys.readouterr().err


def test_past_as_newest_is_reported_and_refuses_what_it_cannot_ablate(
    trained_checkpoint: Path, sim_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = [str(trained_checkpoint), str(sim_root), "--split", "train", "--device", "cpu", "--quiet"]
    assert main(base + ["--past-as-newest", "--json", str(tmp_path / "still.json")]) == 0
    report = json.loads((tmp_path / "still.json").read_text())
    assert report["past_as_newest"] is True and report["overall"]["frames"] == 2 * 4
    for extra in (["--full-scan"], ["--plots", str(tmp_path / "p")]):
        assert main(base + ["--past-as-newest"] + extra) == 2
        assert "--past-as-newest" in capsys.readouterr().err


def test_plots_draw_the_boxes_the_service_would_answer(
    trained_checkpoint: Path, sim_root: Path, tmp_path: Path
) -> None:
    """--plots draws the boxes at or above the operating threshold (--score-threshold changes it), not every box."""
    from rafd.viz.drawing import PRED_COLOUR

    red = {}
    for threshold in ("0.0", "1.0"):
        plots = tmp_path / threshold
        argv = [str(trained_checkpoint), str(sim_root), "--split", "train", "--device", "cpu", "--quiet"]
        assert main([*argv, "--plots", str(plots), "--examples", "1", "--score-threshold", threshold]) == 0
        (example,) = plots.glob("example_*.png")
        picture = cv2.imread(str(example))
        assert picture is not None
        scan = picture[: picture.shape[1]]  # the square scan above the legend strip
        red[threshold] = int((np.abs(scan.astype(int) - np.array(PRED_COLOUR)) < 60).all(-1).sum())
    assert red["0.0"] > 50  # every decoded box is drawn at threshold 0
    assert red["1.0"] == 0  # none reaches 1.0: nothing is drawn


def test_tracking_scores_tracks_and_velocities(trained_checkpoint: Path, sim_root: Path, tmp_path: Path) -> None:
    out_json = tmp_path / "metrics.json"
    args = [str(trained_checkpoint), str(sim_root), "--split", "train", "--device", "cpu", "--quiet"]
    code = main(args + ["--warm-up-windows", "--tracking", "--json", str(out_json)])
    assert code == 0
    report = json.loads(out_json.read_text())
    tracking = report["tracking"]
    assert tracking["frames"] == report["overall"]["frames"] and tracking["sequences"] == 2
    assert tracking["velocity_truth"] == "simulator"  # the simulated drives carry their true velocities
    for key in ("HOTA", "DetA", "AssA", "MOTA", "IDF1", "IDSW"):
        assert key in tracking["tracking"]
    assert set(tracking["candidates"]) == {"flow_centre", "flow_box", "filter", "filter_flow"}
    assert {"detections", "confirmed"} <= set(tracking["time_helps_detection"])
    assert main(args + ["--tracking", "--past-as-newest"]) == 2


def test_calibrate_far_writes_a_far_threshold_that_the_report_scores_at(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    from rafd.assets import default_checkpoint
    from rafd.model.checkpoint import read_checkpoint
    from rafd.sim import simulate_sequence

    simulate_sequence(tmp_path / "scans" / "seq", seed=9, num_frames=5, split="val", size=640)  # 9 tiles, +-55 m
    checkpoint = Path(shutil.copy(default_checkpoint(), tmp_path / "model.pt"))
    out_json = tmp_path / "metrics.json"
    args = [str(checkpoint), str(tmp_path / "scans"), "--split", "val", "--device", "cpu", "--quiet"]
    assert main([*args, "--full-scan", "--calibrate-far", "20:50", "--json", str(out_json)]) == 0
    meta = read_checkpoint(checkpoint)[2]
    far = meta["operating_threshold_far"]
    assert far["from_m"] == 20.0 and meta["operating_threshold"] <= far["threshold"] <= 1.0
    assert meta["operating_point_far"]["fp_per_frame_upper_bound"] <= 50.0
    assert "far operating threshold" in capsys.readouterr().out
    overall = json.loads(out_json.read_text())["overall"]
    assert overall["far_score_threshold"] == far and overall["score_threshold"] == meta["operating_threshold"]
    # the crop protocol cannot calibrate a far threshold; a malformed one is refused by the parser
    assert main([*args, "--calibrate-far", "20:1"]) == 2
    assert "--full-scan" in capsys.readouterr().err
    assert main([*args, "--full-scan", "--calibrate-far", "20:1", "--score-threshold", "0.5"]) == 2
    assert "--score-threshold" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:
        main([*args, "--full-scan", "--calibrate-far", "twenty"])
    assert refused.value.code == 2 and "FROM_M:FP_PER_FRAME" in capsys.readouterr().err
