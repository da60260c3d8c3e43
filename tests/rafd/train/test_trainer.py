"""Training loop: overfits a fixed batch, is deterministic for a seed, and resumes exactly."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from rafd.config import RaFDConfig
from rafd.data.collate import Collator
from rafd.data.windows import open_windows
from rafd.train.config import RunConfig, TrainConfig
from rafd.train.distributed import DistContext
from rafd.train.losses import LOSS_TERMS
from rafd.train.trainer import Trainer, optimizer_state_path

CPU = DistContext()


def _train_cfg(**changes: object) -> TrainConfig:
    base = dict(epochs=1, batch_size=2, seed=3, device="cpu", progress=False, max_steps_per_epoch=2, val_every=0)
    base.update(changes)
    return TrainConfig(**base)  # type: ignore[arg-type]


def _weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.model.state_dict().items()}


def _assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), f"{key} differs"


def test_a_few_steps_reduce_the_loss_on_a_fixed_batch(tiny_root: Path, tiny_cfg: RaFDConfig) -> None:
    dataset = open_windows(tiny_root, "train", tiny_cfg)
    trainer = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(lr=2e-3)), dataset, None, CPU)
    batch = Collator(tiny_cfg)([dataset[i] for i in range(min(4, len(dataset)))])
    assert batch.targets["box_mask"].sum() > 0, "the fixture should hold objects"
    losses = [trainer.train_step(batch)[LOSS_TERMS.index("total")].item() for _ in range(12)]
    assert all(torch.isfinite(torch.tensor(losses)))
    assert losses[-1] < 0.7 * losses[0], losses


def test_same_seed_gives_identical_weights(tiny_root: Path, tiny_cfg: RaFDConfig) -> None:
    dataset = open_windows(tiny_root, "train", tiny_cfg)
    runs = []
    for seed in (3, 3, 4):
        trainer = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(seed=seed)), dataset, None, CPU)
        trainer.fit()
        runs.append(_weights(trainer))
    _assert_same(runs[0], runs[1])
    assert any(not torch.equal(runs[0][k], runs[2][k]) for k in runs[0]), "another seed must change the weights"


def test_resume_equals_uninterrupted_run(tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path: Path) -> None:
    dataset = open_windows(tiny_root, "train", tiny_cfg)
    full = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(epochs=2)), dataset, tmp_path / "full.pt", CPU)
    full.fit()

    first = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(epochs=1)), dataset, tmp_path / "half.pt", CPU)
    first.fit()
    assert (tmp_path / "half.pt").is_file() and optimizer_state_path(tmp_path / "half.pt").is_file()
    resumed = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(epochs=2)), dataset, tmp_path / "resumed.pt", CPU)
    resumed.resume(tmp_path / "half.pt")
    assert (resumed.epoch, resumed.step) == (1, first.step)
    resumed.fit()

    assert resumed.step == full.step
    _assert_same(_weights(full), _weights(resumed))
    assert [h["loss_total"] for h in resumed.history] == pytest.approx(
        [h["loss_total"] for h in full.history], rel=0, abs=0
    )


def test_resume_without_optimizer_state_is_a_clear_error(tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path: Path) -> None:
    dataset = open_windows(tiny_root, "train", tiny_cfg)
    trainer = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg()), dataset, tmp_path / "a.pt", CPU)
    trainer.fit()
    optimizer_state_path(tmp_path / "a.pt").unlink()
    with pytest.raises(FileNotFoundError, match="optim.pt"):
        Trainer(RunConfig(model=tiny_cfg, train=_train_cfg()), dataset, None, CPU).resume(tmp_path / "a.pt")


def test_init_from_a_single_frame_model_copies_its_encoder_and_head(tiny_root: Path, tmp_path: Path) -> None:
    """Two-stage recipe: a 2-frame run starts from a trained single-frame model. With pre-norm propagation the
    fresh multi-frame model then predicts exactly what the single-frame model predicts on the newest frame."""
    import dataclasses

    base = RaFDConfig.tiny(input_size=64, num_frames=1)
    single_cfg = base.replace(propagation=dataclasses.replace(base.propagation, norm="pre"))
    single = Trainer(
        RunConfig(model=single_cfg, train=_train_cfg()),
        open_windows(tiny_root, "train", single_cfg),
        tmp_path / "single.pt",
        CPU,
    )
    single.fit()
    multi_cfg = single_cfg.replace(num_frames=2)
    dataset = open_windows(tiny_root, "train", multi_cfg)
    multi = Trainer(RunConfig(model=multi_cfg, train=_train_cfg()), dataset, tmp_path / "multi.pt", CPU)
    report = multi.initialise_from(tmp_path / "single.pt")
    assert report["skipped"] == [] and report["copied"]
    assert {name.split(".")[0] for name in report["fresh"]} == {"flow", "propagation"}
    trained = single.model.state_dict()
    for name in report["copied"]:
        assert torch.equal(multi.model.state_dict()[name], trained[name]), name
    assert multi.run_meta["init"] == str(tmp_path / "single.pt")
    batch = Collator(multi_cfg)([dataset[0], dataset[1]])
    single.model.eval(), multi.model.eval()
    with torch.no_grad():
        both = multi.model(batch.frames, batch.poses)
        newest = single.model(batch.frames[:, -1:], batch.poses[:, -1:])
    for key in ("heatmap", "boxes", "scores"):
        torch.testing.assert_close(both[key], newest[key], atol=1e-5, rtol=0)
    assert multi.epoch == 0 and multi.history == []  # a new run: schedule and epochs start fresh


def test_init_refuses_a_model_that_reads_other_input(tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path: Path) -> None:
    other = tiny_cfg.replace(input_size=128)
    Trainer(
        RunConfig(model=other, train=_train_cfg()), open_windows(tiny_root, "train", other), tmp_path / "other.pt", CPU
    ).fit()
    trainer = Trainer(
        RunConfig(model=tiny_cfg, train=_train_cfg()), open_windows(tiny_root, "train", tiny_cfg), None, CPU
    )
    before = _weights(trainer)
    with pytest.raises(ValueError, match="input_size"):
        trainer.initialise_from(tmp_path / "other.pt")
    _assert_same(before, _weights(trainer))  # nothing half-copied


def test_a_frozen_encoder_keeps_its_weights_and_batchnorm_statistics(tiny_root: Path, tiny_cfg: RaFDConfig) -> None:
    dataset = open_windows(tiny_root, "train", tiny_cfg)
    trainer = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(lr=2e-3, freeze=("encoder",))), dataset, None, CPU)
    before = _weights(trainer)
    assert any("running_mean" in key for key in before if key.startswith("encoder."))  # BatchNorm to keep
    trainer.fit()
    after = _weights(trainer)
    encoder = [key for key in before if key.startswith("encoder.")]
    assert encoder and all(torch.equal(before[key], after[key]) for key in encoder)
    changed = {key.split(".")[0] for key in before if not torch.equal(before[key], after[key])}
    assert {"flow", "propagation", "head"} <= changed  # the rest trains
    trained = {id(p) for group in trainer.optimizer.param_groups for p in group["params"]}
    assert not any(id(p) in trained for p in trainer.model.encoder.parameters())


def test_resuming_with_other_frozen_parts_is_a_clear_error(
    tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path: Path
) -> None:
    dataset = open_windows(tiny_root, "train", tiny_cfg)
    Trainer(
        RunConfig(model=tiny_cfg, train=_train_cfg(freeze=("encoder",))), dataset, tmp_path / "frozen.pt", CPU
    ).fit()
    other = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(epochs=2)), dataset, None, CPU)
    before = _weights(other)
    with pytest.raises(ValueError, match="trained freezing encoder, this run freezes nothing"):
        other.resume(tmp_path / "frozen.pt")
    _assert_same(before, _weights(other))  # refused before any weight was copied
    same = Trainer(RunConfig(model=tiny_cfg, train=_train_cfg(epochs=2, freeze=("encoder",))), dataset, None, CPU)
    same.resume(tmp_path / "frozen.pt")
    assert same.epoch == 1


def test_freeze_refuses_unknown_or_missing_parts(tiny_root: Path) -> None:
    with pytest.raises(ValueError, match="not parts of the network"):
        _train_cfg(freeze=("backbone",))
    single = RaFDConfig.tiny(input_size=64, num_frames=1)
    with pytest.raises(ValueError, match="no flow"):
        Trainer(
            RunConfig(model=single, train=_train_cfg(freeze=("flow",))),
            open_windows(tiny_root, "train", single),
            None,
            CPU,
        )
