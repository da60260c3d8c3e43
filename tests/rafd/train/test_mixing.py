"""MixedWindows: every primary window once per epoch, mix windows topped up to the share, in a seeded walk that
visits every mix window equally often and is a function of (seed, epoch, slot) only."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from rafd.train.mixing import MixedWindows


class _Recorder:
    """A window dataset stand-in: answers a key with where it came from."""

    def __init__(self, name: str, size: int) -> None:
        self.name, self.size = name, size
        self.sequences = [f"{name}_seq"]

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, key: tuple[int, int]) -> dict[str, Any]:
        epoch, index = key
        assert 0 <= index < self.size
        return {"root": self.name, "epoch": epoch, "index": index}


@pytest.mark.parametrize(("primary", "share", "per_epoch"), [(11, 0.5, 11), (11, 0.25, 4), (8, 0.75, 24), (1, 0.1, 1)])
def test_the_share_fixes_the_mix_windows_per_epoch(primary: int, share: float, per_epoch: int) -> None:
    mixed = MixedWindows(_Recorder("real", primary), _Recorder("sim", 300), share)
    assert mixed.per_epoch == per_epoch and len(mixed) == primary + per_epoch


def test_every_primary_window_once_per_epoch_then_mix_windows() -> None:
    mixed = MixedWindows(_Recorder("real", 11), _Recorder("sim", 40), 0.5, seed=3)
    epoch = [mixed[(2, slot)] for slot in range(len(mixed))]
    assert [w["index"] for w in epoch if w["root"] == "real"] == list(range(11))
    mix = [w for w in epoch if w["root"] == "sim"]
    assert len(mix) == 11 and len({w["index"] for w in mix}) == 11  # no repeat within an epoch of a longer walk
    assert all(w["epoch"] == 2 for w in epoch)  # the epoch reaches each dataset: its augmentation is drawn from it
    assert mixed.sequences == ["real_seq", "sim_seq"]
    assert mixed[5] == mixed[(0, 5)]  # a plain index is epoch 0's slot


def test_the_walk_visits_every_mix_window_equally_often_and_repeats_for_a_seed() -> None:
    mixed = MixedWindows(_Recorder("real", 5), _Recorder("sim", 12), 0.5, seed=7)
    assert mixed.per_epoch == 5
    epochs = 12  # 60 slots = 5 laps of the 12 mix windows
    seen = Counter(mixed.mix_index(e, s) for e in range(epochs) for s in range(mixed.per_epoch))
    assert set(seen) == set(range(12)) and set(seen.values()) == {5}
    again = MixedWindows(_Recorder("real", 5), _Recorder("sim", 12), 0.5, seed=7)
    other = MixedWindows(_Recorder("real", 5), _Recorder("sim", 12), 0.5, seed=8)
    walk = [mixed.mix_index(e, s) for e in range(3) for s in range(5)]
    assert walk == [again.mix_index(e, s) for e in range(3) for s in range(5)]  # a resumed run draws the same
    assert walk != [other.mix_index(e, s) for e in range(3) for s in range(5)]
    assert [mixed.mix_index(1, s) for s in range(5)] != [mixed.mix_index(0, s) for s in range(5)]


@pytest.mark.parametrize("share", [0.0, 1.0, -0.2, 1.5])
def test_a_share_outside_zero_one_is_refused(share: float) -> None:
    with pytest.raises(ValueError, match=r"share must be in \(0, 1\)"):
        MixedWindows(_Recorder("real", 3), _Recorder("sim", 3), share)


def test_empty_data_and_out_of_range_slots_are_refused() -> None:
    with pytest.raises(ValueError, match="need windows"):
        MixedWindows(_Recorder("real", 0), _Recorder("sim", 3), 0.5)
    mixed = MixedWindows(_Recorder("real", 3), _Recorder("sim", 3), 0.5)
    with pytest.raises(IndexError, match="6 windows per epoch"):
        mixed[(0, 6)]


def test_a_training_run_mixes_a_second_root_and_records_it(tiny_root: Path, tmp_path: Path) -> None:
    """Two roots through train(): each epoch holds ROOT's windows and the mix root's share; the checkpoint records
    the mix, and the augmentation overrides change ROOT's augmentation only."""
    from rafd.model.checkpoint import read_checkpoint
    from rafd.train.config import RunConfig
    from rafd.train.recipes import recipe_config
    from rafd.train.run import DataSource, TrainRun, train

    out = tmp_path / "mixed.pt"
    config = recipe_config("tiny").overridden(
        {
            "model.num_frames": 2,
            "model.input_size": 64,
            "train.epochs": 1,
            "train.batch_size": 2,
            "train.device": "cpu",
            "train.progress": False,
            "train.threads": 1,
            "train.num_workers": 0,
            "data.max_windows": 2,
            "data.mix_share": 0.6,
            "data.augment.max_rotation_deg": 180.0,
            "data.augment.shift_max_m": 3.0,
            "data.augment.shift_probability": 0.5,
        }
    )
    run = TrainRun(config, DataSource(tiny_root, ("train",)), out, mix=DataSource(tiny_root, ("train",)))
    history = train(run)
    assert history[0]["windows"] == 2 + 3  # 2 primary windows and round(2 * 0.6 / 0.4) = 3 mix windows
    _, _, meta = read_checkpoint(out)
    stored = RunConfig.from_dict(meta["run_config"])
    assert meta["mix"]["windows_per_epoch"] == 3 and stored.data.mix_share == 0.6
    assert stored.data.augment.max_rotation_deg == 180.0 and stored.data.augment.shift_max_m == 3.0
    assert stored.data.mix_augment.max_rotation_deg == 15.0 and stored.data.mix_augment.shift_max_m == 0.0
