"""RadarWindowDataset: discovery, split filter, prepared poses and scan cache, windows, crop protocol, augmentation."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from rafd.config import RaFDConfig
from rafd.data import RadarWindowDataset, find_sequences, load_image, read_sequence
from rafd.data.augment import Augmentation
from rafd.geometry import centre_crop
from rafd.sim import simulate_sequence

CFG = RaFDConfig.tiny()  # 128 px crop (+-11.1 m), 4 frames
HALF = CFG.input_size / 2 * CFG.resolution


@pytest.fixture(scope="module")
def root(sim_truth_and_folder, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two sequences: the 10-frame train_good_weather simulation with pedestrians added near the radar, and
    a 6-frame 256 px `test` one, in nested folders."""
    root = tmp_path_factory.mktemp("windows")
    train = Path(shutil.copytree(sim_truth_and_folder[1], root / "good" / "sim_31_0"))
    path = train / "annotations" / "annotations.json"
    entries = json.loads(path.read_text())
    walker = {"position": [186.0, 180.0, 6.0, 6.0], "rotation": 0.0}  # 384 px scan: centre (189, 183) px
    group = {"position": [200.0, 200.0, 12.0, 10.0], "rotation": 10.0}
    entries.append({"id": 901, "class_name": "pedestrian", "bboxes": [walker] * 10})
    entries.append({"id": 902, "class_name": "group_of_pedestrians", "bboxes": [group] * 10})
    path.write_text(json.dumps(entries))
    simulate_sequence(root / "other" / "sim_test", seed=5, num_frames=6, split="test", size=256)
    return root


def test_discovery_split_filter_and_window_counts(root: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert [p.name for p in find_sequences(root)] == ["sim_31_0", "sim_test"]
    assert len(RadarWindowDataset(root, split=None, cfg=CFG)) == 7 + 3
    assert len(RadarWindowDataset(root, split="train_good_weather", cfg=CFG)) == 7
    assert len(RadarWindowDataset(root, split="test", cfg=CFG)) == 3
    assert len(RadarWindowDataset(root, split=["test", "train_good_weather"], cfg=CFG)) == 10
    strided = RadarWindowDataset(root, split="train_good_weather", cfg=CFG, stride=2)
    assert [strided[k]["frame"] for k in range(len(strided))] == [4, 6, 8, 10]
    assert len(RadarWindowDataset(root / "other" / "sim_test", split=None, cfg=CFG.replace(num_frames=2))) == 5
    with caplog.at_level(logging.WARNING, logger="rafd.data.dataset"):
        assert len(RadarWindowDataset(root, split="train_good_and_bad_weather", cfg=CFG)) == 0
    assert "splits found" in caplog.text
    with pytest.raises(FileNotFoundError, match="no sequence folders"):
        RadarWindowDataset(root / "good" / "sim_31_0" / "annotations", split=None, cfg=CFG)


def test_window_content_follows_the_protocol(root: Path, sim_truth_and_folder) -> None:
    truth, _ = sim_truth_and_folder
    dataset = RadarWindowDataset(root, split="train_good_weather", cfg=CFG)
    sequence = read_sequence(root / "good" / "sim_31_0")
    for index in range(len(dataset)):
        window = dataset[index]
        assert window["sequence"] == "sim_31_0" and window["frame"] == index + 4
        assert window["frames"].shape == (4, 128, 128) and window["frames"].dtype == np.uint8
        np.testing.assert_allclose(window["poses"], truth.poses[index : index + 4], rtol=0, atol=1e-12)
        assert window["poses"].dtype == np.float64
        for t in range(4):
            k = index + t
            np.testing.assert_array_equal(window["frames"][t], centre_crop(truth.images[k], 128))
            expected = sorted(
                (o.id, o.class_name)
                for o in truth.objects
                if np.isfinite(o.boxes[k, 0])
                and np.all(np.abs(o.boxes[k, :2]) < HALF)
                and o.class_name not in ("pedestrian", "group_of_pedestrians")
            )
            assert sorted(zip(window["ids"][t].tolist(), window["classes"][t])) == expected
            assert window["boxes"][t].shape == (len(expected), 5) and window["ids"][t].dtype == np.int64
            for object_id, box in zip(window["ids"][t], window["boxes"][t]):
                np.testing.assert_allclose(box, next(o.boxes[k] for o in truth.objects if o.id == object_id), atol=1e-9)
        # The added pedestrians sit inside the crop and are dropped; the reader still has them.
        assert {901, 902} <= {o.id for o in sequence.frames[index].objects}
        assert not {901, 902} & set(np.concatenate(window["ids"]).tolist())
    assert sum(len(b) for k in range(len(dataset)) for b in dataset[k]["boxes"]) > 0


def test_windows_collate_into_a_batch(root: Path) -> None:
    from rafd.data.collate import Collator

    dataset = RadarWindowDataset(root, split=None, cfg=CFG)
    batch = Collator(CFG)([dataset[0], dataset[len(dataset) - 1]])
    assert tuple(batch.frames.shape) == (2, 4, 1, 128, 128) and tuple(batch.poses.shape) == (2, 4, 3)
    assert tuple(batch.targets["heatmap"].shape) == (2, 1, 32, 32)
    assert tuple(batch.targets["flow"].shape) == (2, 3, 2, 32, 32)
    assert batch.sequences == ["sim_31_0", "sim_test"] and batch.frame_numbers == [4, 6]


def test_windows_from_the_prepared_cache_equal_windows_decoded_from_the_pngs(root: Path, tmp_path: Path) -> None:
    from rafd.cli.prepare import main as prepare_main

    assert prepare_main([str(root), "--out", str(tmp_path / "cache"), "--crop-size", "192", "--workers", "2"]) == 0
    for augment in (False, True):
        decoded = RadarWindowDataset(root, split=None, cfg=CFG, augment=augment, seed=3)
        cached = RadarWindowDataset(root, split=None, cfg=CFG, augment=augment, seed=3, cache=tmp_path / "cache")
        for key in [(0, 0), (1, 3), (2, len(decoded) - 1)]:
            a, b = decoded[key], cached[key]
            np.testing.assert_array_equal(a["frames"], b["frames"])
            assert a["augmentation"] == b["augmentation"]
            assert all(np.array_equal(x, y) for x, y in zip(a["boxes"], b["boxes"]))
    # resumable: a second run finds every sequence complete
    assert prepare_main([str(root), "--out", str(tmp_path / "cache"), "--crop-size", "192"]) == 0


def test_cache_problems_name_the_fix(root: Path, tmp_path: Path) -> None:
    from rafd.cli.prepare import main as prepare_main
    from rafd.data.cache import CacheError

    with pytest.raises(CacheError, match="rafd prepare"):  # not prepared
        RadarWindowDataset(root, split="test", cfg=CFG, cache=tmp_path / "none")
    assert prepare_main([str(root), "--out", str(tmp_path / "small"), "--crop-size", "128", "--split", "test"]) == 0
    RadarWindowDataset(root, split="test", cfg=CFG, cache=tmp_path / "small")  # enough without rotations
    with pytest.raises(CacheError, match="--crop-size 184"):  # rotations need 128 * sqrt(2) + 2 px
        RadarWindowDataset(root, split="test", cfg=CFG, augment=True, cache=tmp_path / "small")


def test_only_the_selected_splits_are_read(root: Path, tmp_path: Path) -> None:
    """meta.json first: a sequence of another split is never read, even when it could not be."""
    broken = Path(shutil.copytree(root / "other" / "sim_test", tmp_path / "mixed" / "broken"))
    shutil.copytree(root / "good" / "sim_31_0", tmp_path / "mixed" / "good")
    (broken / "annotations" / "annotations.json").write_text("{not json")
    (broken / "ego_poses.csv").unlink()
    assert len(RadarWindowDataset(tmp_path / "mixed", split="train_good_weather", cfg=CFG)) == 7
    with pytest.raises(ValueError, match="malformed JSON"):
        RadarWindowDataset(tmp_path / "mixed", split="test", cfg=CFG)


def test_missing_poses_are_an_error_naming_rafd_odometry_unless_estimation_is_asked(
    root: Path, tmp_path: Path, caplog
) -> None:
    from rafd.data.dataset import MissingPosesError

    folder = Path(shutil.copytree(root / "other" / "sim_test", tmp_path / "noposes" / "seq"))
    (folder / "ego_poses.csv").unlink()
    with pytest.raises(MissingPosesError, match=rf"rafd-odometry {tmp_path / 'noposes'}"):
        RadarWindowDataset(tmp_path / "noposes", split=None, cfg=CFG)
    with caplog.at_level(logging.INFO, logger="rafd.data.reader"):
        dataset = RadarWindowDataset(tmp_path / "noposes", split=None, cfg=CFG, estimate_poses=True)
    assert len(dataset) == 3 and "radar odometry" in caplog.text


def test_augmentation_depends_only_on_seed_epoch_and_window(root: Path) -> None:
    import pickle

    dataset = RadarWindowDataset(root, split="train_good_weather", cfg=CFG, augment=True, seed=7)
    first = [dataset[(2, k)]["augmentation"] for k in range(len(dataset))]
    dataset[(0, 1)], dataset[(5, 4)]  # other draws in between change nothing
    copy = pickle.loads(pickle.dumps(dataset))  # as a DataLoader worker holds it
    assert [copy[(2, k)]["augmentation"] for k in reversed(range(len(dataset)))][::-1] == first
    assert [dataset[(3, k)]["augmentation"] for k in range(len(dataset))] != first  # a new epoch, new draws
    assert dataset[4]["augmentation"] == dataset[(0, 4)]["augmentation"]


def test_augmented_windows_are_seeded_and_consistent(root: Path) -> None:
    plain = RadarWindowDataset(root, split="train_good_weather", cfg=CFG)
    first = RadarWindowDataset(root, split="train_good_weather", cfg=CFG, augment=True, seed=7)
    again = RadarWindowDataset(root, split="train_good_weather", cfg=CFG, augment=True, seed=7)
    other = RadarWindowDataset(root, split="train_good_weather", cfg=CFG, augment=True, seed=8)
    drawn = [first[k] for k in range(len(first))]
    assert [w["augmentation"] for w in drawn] == [again[k]["augmentation"] for k in range(len(again))]
    assert [w["augmentation"] for w in drawn] != [other[k]["augmentation"] for k in range(len(other))]
    assert any(w["augmentation"]["flip"] for w in drawn) and any(w["augmentation"]["angle"] != 0 for w in drawn)
    for k, window in enumerate(drawn):
        augmentation = Augmentation(**window["augmentation"])
        expected = plain.window(k, augmentation)
        np.testing.assert_array_equal(window["frames"], expected["frames"])
        np.testing.assert_allclose(window["poses"], augmentation.poses(plain[k]["poses"]), atol=1e-12)
        full = [plain.sequences[0].frames[k + t].image_path for t in range(4)]
        for t in range(4):
            np.testing.assert_array_equal(window["frames"][t], augmentation.image(load_image(full[t]), 128))
            # Every kept box is an augmented original (same id), inside the crop.
            originals = {i: b for i, b in zip(plain.sequences[0].ids[k + t], plain.sequences[0].boxes[k + t])}
            for object_id, box in zip(window["ids"][t], window["boxes"][t]):
                np.testing.assert_allclose(box, augmentation.boxes(originals[object_id][None])[0], atol=1e-12)
                assert np.all(np.abs(box[:2]) < HALF)


def test_unusable_sequences_fail_clearly(root: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="cannot be centre-cropped"):
        RadarWindowDataset(root / "other", split=None, cfg=RaFDConfig.paper().replace(input_size=512))
    with pytest.raises(ValueError, match="resolution"):
        RadarWindowDataset(root / "other", split=None, cfg=CFG.replace(resolution=0.5))
    bare = Path(shutil.copytree(root / "other" / "sim_test", tmp_path / "bare"))
    (bare / "annotations" / "annotations.json").unlink()
    with pytest.raises(FileNotFoundError, match="annotations.json"):
        RadarWindowDataset(bare, split=None, cfg=CFG)


def test_polar_only_folders_give_the_windows_of_their_cartesian_twin(tmp_path: Path) -> None:
    """A folder holding only Navtech_Polar/ trains like the Cartesian one, via the reader's conversion and the cache."""
    from rafd.cli.odometry import main as odometry_main
    from rafd.cli.prepare import main as prepare_main

    twin = simulate_sequence(
        tmp_path / "twin" / "seq", seed=4, num_frames=6, split="test", size=1152, polar=True, poses=False
    )
    polar_only = Path(shutil.copytree(twin, tmp_path / "polar" / "seq"))
    shutil.rmtree(polar_only / "Navtech_Cartesian")
    (polar_only / "Navtech_Cartesian.txt").unlink()
    assert odometry_main([str(tmp_path / "polar")]) == 0  # poses from the converted scans
    assert prepare_main([str(tmp_path / "polar"), "--out", str(tmp_path / "cache"), "--crop-size", "256"]) == 0
    decoded = RadarWindowDataset(tmp_path / "polar", split="test", cfg=CFG)
    cached = RadarWindowDataset(tmp_path / "polar", split="test", cfg=CFG, cache=tmp_path / "cache")
    assert len(decoded) == len(cached) == 3
    np.testing.assert_array_equal(decoded[2]["frames"], cached[2]["frames"])
    assert decoded[2]["frames"].shape == (4, 128, 128) and decoded[2]["frames"].mean() > 1
