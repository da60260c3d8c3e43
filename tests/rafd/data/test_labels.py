"""Labels of native folders: the box text a labeller writes, the timestamp-keyed label file, MVDNet's label_2d files
(crafted and the published frame's), and ignore regions through the dataset, the targets and the evaluation."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from rafd.config import RaFDConfig
from rafd.data import read_sequence
from rafd.data.dataset import RadarWindowDataset
from rafd.data.labels import (
    IGNORE_CLASS,
    LABELLED_AREA_KEY,
    index_by_frame,
    outside_square,
    parse_box_lines,
    to_annotations,
    write_annotations,
)
from rafd.data.mvdnet_labels import read_mvdnet_labels
from rafd.data.targets import build_targets
from rafd.eval.predict import outside_ignored
from rafd.geometry import box_corners, points_in_boxes
from tests.rafd.data.test_native_folder import STAMPS, write_folder

TEXT = f"""# a comment
{STAMPS[0]} 1 car 5.0 6.0 2.0 4.5 30  # trailing comment
{STAMPS[1]} 1 car 5.5 8.0 2.0 4.5 30
{STAMPS[1]} 7 ignore -6.0 3.0 3.0 3.0 0
"""


def test_box_text_becomes_a_timestamp_keyed_radiate_label_file(tmp_path: Path):
    boxes = parse_box_lines(TEXT.splitlines())
    assert [(b.timestamp_us, b.track, b.class_name) for b in boxes] == [
        (STAMPS[0], 1, "car"),
        (STAMPS[1], 1, "car"),
        (STAMPS[1], 7, IGNORE_CLASS),
    ]
    annotations = to_annotations(boxes)
    path = write_annotations(tmp_path / "labels.json", annotations)
    tracks = json.loads(path.read_text())
    assert [t["id"] for t in tracks] == [1, 7] and set(tracks[0]["bboxes"]) == {str(STAMPS[0]), str(STAMPS[1])}
    box = tracks[0]["bboxes"][str(STAMPS[0])]
    assert box["rotation"] == pytest.approx(30.0) and box["position"][2] == pytest.approx(2.0 / 0.173611, abs=1e-3)
    indexed = index_by_frame(tracks, {STAMPS[1]: 1, STAMPS[3]: 2})  # a folder with two of the scans
    assert indexed[0]["bboxes"] == [tracks[0]["bboxes"][str(STAMPS[1])], []]


@pytest.mark.parametrize(
    "line, message",
    [
        ("1 2 car 1 2 3", "expected 8 fields"),
        ("1 2 tram 1 2 3 4 5", "is not one of"),
        ("1 2 car 1 2 -3 4 5", "sizes must be positive"),
        ("x 2 car 1 2 3 4 5", "invalid literal"),
    ],
)
def test_bad_box_lines_name_the_line(line: str, message: str):
    with pytest.raises(ValueError, match=message):
        parse_box_lines(["# header", line], "boxes.txt")


def test_tracks_keep_one_class_and_one_box_per_scan():
    with pytest.raises(ValueError, match="both car and van"):
        to_annotations(parse_box_lines([f"{STAMPS[0]} 1 car 1 1 2 4 0", f"{STAMPS[1]} 1 van 1 1 2 4 0"]))
    with pytest.raises(ValueError, match="two boxes in scan"):
        to_annotations(parse_box_lines([f"{STAMPS[0]} 1 car 1 1 2 4 0", f"{STAMPS[0]} 1 car 3 1 2 4 0"]))


def test_a_native_folder_reads_its_label_file_and_the_dataset_keeps_ignore_apart(tmp_path: Path):
    folder = write_folder(tmp_path / "seq", STAMPS[:2])
    write_annotations(folder / "annotations" / "annotations.json", to_annotations(parse_box_lines(TEXT.splitlines())))
    (folder / "meta.json").write_text(json.dumps({"name": "seq", "set": "train"}))
    sequence = read_sequence(folder, estimate_poses=False)
    assert [[o.class_name for o in f.objects] for f in sequence.frames] == [["car"], ["car", IGNORE_CLASS]]
    np.testing.assert_allclose(sequence.frames[0].objects[0].box, [5.0, 6.0, 2.0, 4.5, np.radians(30)], atol=1e-3)
    (folder / "ego_poses.csv").write_text(
        f"frame,timestamp,x,y,yaw\n1,{sequence.frames[0].timestamp_text},0,0,0\n"
        f"2,{sequence.frames[1].timestamp_text},0,0.5,0\n"
    )
    window = RadarWindowDataset(tmp_path, cfg=RaFDConfig.tiny(num_frames=1))[1]
    assert len(window["boxes"][-1]) == 1 and len(window["ignore"][-1]) == 1  # ignore is no vehicle


def test_ignore_regions_are_no_heatmap_negatives_and_no_false_positives():
    cfg = RaFDConfig.tiny(num_frames=1)
    car = np.array([[5.0, 5.0, 2.0, 4.5, 0.0]])
    ignore = np.array([[-6.0, 3.0, 3.0, 3.0, 0.0]])
    weight = build_targets([car], [np.array([1])], np.zeros((1, 3)), cfg, ignore)["heatmap_weight"][0]
    assert weight.min() == 0.0 and weight.max() == 1.0 and weight.size - 30 < weight.sum() < weight.size  # 3 x 3 m
    assert build_targets([car], [np.array([1])], np.zeros((1, 3)), cfg)["heatmap_weight"].min() == 1.0
    predictions = np.array([[-6.2, 3.1, 2.0, 4.5, 0.0, 0.9], [5.0, 5.0, 2.0, 4.5, 0.0, 0.8]])
    np.testing.assert_array_equal(outside_ignored(predictions, ignore), predictions[1:])


def test_outside_square_covers_the_scan_beyond_the_labelled_square_once():
    boxes = outside_square(30.0, 200.0)
    grid = np.stack(np.meshgrid(np.linspace(-199, 199, 81), np.linspace(-199, 199, 81)), -1).reshape(-1, 2)
    covered = points_in_boxes(grid, boxes).sum(axis=1)
    inside = (np.abs(grid) < 30.0).all(axis=1)
    assert (covered[inside] == 0).all() and (covered[~inside] == 1).all()  # no overlap, no gap, no label lost
    with pytest.raises(ValueError, match=r"in \(0, 200"):
        outside_square(250.0, 200.0)


def test_a_labelled_area_in_meta_json_ignores_the_scan_outside_it(tmp_path: Path):
    folder = write_folder(tmp_path / "seq", STAMPS[:2])
    write_annotations(folder / "annotations" / "annotations.json", to_annotations(parse_box_lines(TEXT.splitlines())))
    (folder / "meta.json").write_text(json.dumps({"name": "seq", "set": "train", LABELLED_AREA_KEY: 20.0}))
    sequence = read_sequence(folder, estimate_poses=False)
    assert [[o.class_name for o in f.objects] for f in sequence.frames] == [
        ["car"] + [IGNORE_CLASS] * 4,
        ["car", IGNORE_CLASS] + [IGNORE_CLASS] * 4,
    ]
    area = np.array([o.box for o in sequence.frames[0].objects[1:]])
    assert points_in_boxes(np.array([[25.0, 0.0], [0.0, -40.0], [5.0, 6.0]]), area).any(axis=1).tolist() == [
        True,
        True,
        False,  # the car
    ]
    (folder / "meta.json").write_text(json.dumps({"name": "seq", "set": "train", LABELLED_AREA_KEY: "30 m"}))
    with pytest.raises(ValueError, match="labelled_half_m must be a number of metres"):
        read_sequence(folder, estimate_poses=False)


def test_mvdnet_label_files_read_in_this_projects_convention(tmp_path: Path):
    """Crafted: xc right, yc backwards, yaw clockwise on screen -> (xc, -yc, w, l, -yaw)."""
    folder = write_folder(tmp_path / "seq", STAMPS[:2])
    (folder / "label_2d").mkdir()
    (folder / "label_2d" / f"{STAMPS[1]}.txt").write_text("Car 12 3.0 -8.0 2.0 4.5 30.0\nCar 13 -4.0 6.0 2.2 5.0 -90\n")
    labels = read_mvdnet_labels(folder / "label_2d" / f"{STAMPS[1]}.txt")
    assert [(t, c) for t, c, _ in labels] == [(12, "car"), (13, "car")]
    np.testing.assert_allclose(labels[0][2], [3.0, 8.0, 2.0, 4.5, np.radians(-30.0)])
    sequence = read_sequence(folder, estimate_poses=False)
    assert sequence.annotated and not sequence.frames[0].objects and len(sequence.frames[1].objects) == 2
    # the box's corners: a 30-degree clockwise turn on screen leans its long side to the right of forward
    corners = box_corners(labels[0][2][None])[0]
    top = corners[np.argmax(corners[:, 1])]
    assert top[0] > 3.0
    (folder / "label_2d" / "bad.txt").write_text("Car 1 2 3\n")
    with pytest.raises(ValueError, match="expected 'Car"):
        read_mvdnet_labels(folder / "label_2d" / "bad.txt")


def test_the_published_mvdnet_frame_reads_with_its_labels(tmp_path: Path):
    """MVDNet's labels of the one labelled Oxford frame (../shared/oxford_labelled, found beside the Oxford sample)."""
    oxford = os.environ.get("RAFD_OXFORD_SAMPLE")
    labelled = Path(oxford).parent / "oxford_labelled" if oxford else None
    if labelled is None or not (labelled / "labels").is_dir():
        pytest.skip("the MVDNet-labelled Oxford frame is not beside RAFD_OXFORD_SAMPLE (shared/oxford_labelled)")
    scan = next(labelled.glob("*.png"))
    folder = tmp_path / "mvdnet"
    (folder / "radar").mkdir(parents=True)
    os.symlink(scan, folder / "radar" / scan.name)
    os.symlink(labelled / "labels", folder / "label_2d")
    sequence = read_sequence(folder, estimate_poses=False)
    cars = sequence.frames[0].objects
    assert len(cars) == 7 and {c.class_name for c in cars} == {"car"}
    assert all(2.0 < c.box[2] < 3.5 and 4.0 < c.box[3] < 6.0 for c in cars)  # car-sized, width <= length
    # the 3D labels give the same centres with forward = their z
    for car, line in zip(cars, (labelled / "labels" / f"{scan.stem}_label_3d.txt").read_text().splitlines()):
        fields = line.split()
        np.testing.assert_allclose(car.box[:2], [float(fields[11]), float(fields[13])], atol=0.01)
