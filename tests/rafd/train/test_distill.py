"""Heatmap distillation: the soft-target loss, the teacher a checkpoint becomes, and a training run with one."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from rafd.config import RaFDConfig
from rafd.data.collate import Collator
from rafd.data.windows import open_windows
from rafd.model import build_model
from rafd.model.checkpoint import read_checkpoint, save_checkpoint
from rafd.train.config import LossConfig, RunConfig, TrainConfig
from rafd.train.distill import heatmap_distillation, load_teacher
from rafd.train.distributed import DistContext
from rafd.train.losses import LOSS_TERMS, RaFDLoss
from rafd.train.trainer import Trainer


def _narrow(cfg: RaFDConfig) -> RaFDConfig:
    return cfg.replace(neck=dataclasses.replace(cfg.neck, channels=cfg.neck.channels // 2))


def _teacher_checkpoint(path: Path, cfg: RaFDConfig) -> Path:
    torch.manual_seed(5)
    return save_checkpoint(path, build_model(cfg).eval(), cfg)


def test_the_loss_is_zero_where_the_student_agrees_and_pulls_it_towards_the_teacher() -> None:
    generator = torch.Generator().manual_seed(0)
    teacher = torch.randn(2, 1, 8, 8, generator=generator) * 3
    assert heatmap_distillation(teacher.clone(), teacher, torch.tensor(4.0)).item() == pytest.approx(0.0, abs=1e-7)
    student = torch.zeros(2, 1, 8, 8, requires_grad=True)
    optimizer = torch.optim.SGD([student], lr=5.0)
    gaps = []
    for _ in range(30):
        gaps.append((torch.sigmoid(student) - torch.sigmoid(teacher)).abs().mean().item())
        optimizer.zero_grad()
        heatmap_distillation(student, teacher, torch.tensor(1.0)).backward()
        optimizer.step()
    assert gaps[-1] < 0.5 * gaps[0], gaps


def test_the_loss_is_normalised_by_the_labelled_centres() -> None:
    student, teacher = torch.zeros(1, 1, 4, 4), torch.full((1, 1, 4, 4), 2.0)
    one = heatmap_distillation(student, teacher, torch.tensor(1.0))
    assert one.item() > 0
    assert heatmap_distillation(student, teacher, torch.tensor(4.0)).item() == pytest.approx(one.item() / 4)
    assert heatmap_distillation(student, teacher, torch.tensor(0.0)).item() == pytest.approx(one.item())  # at least 1


def test_a_teachers_heatmap_in_the_targets_adds_the_weighted_term() -> None:
    heatmap = torch.zeros(1, 1, 4, 4)
    heatmap[0, 0, 1, 1] = 1.0
    outputs = {"heatmap": torch.zeros(1, 1, 4, 4), **{k: torch.zeros(1, 2, 2) for k in ("pred_offset",)}}
    outputs |= {"pred_log_size": torch.zeros(1, 2, 2), "pred_rotation": torch.zeros(1, 2, 2)}
    targets = {
        "heatmap": heatmap,
        "offset": torch.zeros(1, 2, 2),
        "log_size": torch.zeros(1, 2, 2),
        "rotation": torch.zeros(1, 2, 2),
        "box_mask": torch.tensor([[1.0, 0.0]]),
    }
    plain = RaFDLoss()(outputs, targets)
    assert plain["distill"].item() == 0.0
    taught = RaFDLoss(LossConfig(distill_weight=0.5))(
        outputs, {**targets, "teacher_heatmap": torch.full_like(heatmap, 3)}
    )
    assert taught["distill"].item() > 0
    assert taught["total"].item() == pytest.approx(plain["total"].item() + 0.5 * taught["distill"].item(), rel=1e-6)


def test_a_multi_frame_checkpoint_teaches_a_narrower_single_frame_student(tmp_path: Path, tiny_cfg: RaFDConfig) -> None:
    path = _teacher_checkpoint(tmp_path / "teacher.pt", tiny_cfg)
    student = _narrow(tiny_cfg).replace(num_frames=1)
    teacher = load_teacher(path, student)
    assert not any(p.requires_grad for p in teacher.parameters())
    teacher.train()
    assert not teacher.model.training  # BatchNorm keeps the teacher's statistics under the student's train()
    # its heatmap is the teacher's own single-frame part: the checkpoint's encoder and head on the newest frame
    single = build_model(tiny_cfg.replace(num_frames=1)).eval()
    single.load_state_dict(read_checkpoint(path)[0], strict=False)
    frames = torch.rand(2, 1, 1, tiny_cfg.input_size, tiny_cfg.input_size)
    poses = torch.zeros(2, 1, 3)
    with torch.no_grad():
        assert torch.allclose(teacher(frames, poses), single(frames, poses)["heatmap"])


def test_a_teacher_that_cannot_teach_is_refused(tmp_path: Path, tiny_cfg: RaFDConfig) -> None:
    path = _teacher_checkpoint(tmp_path / "teacher.pt", tiny_cfg.replace(num_frames=1))
    with pytest.raises(ValueError, match="fewer than the student's"):
        load_teacher(path, tiny_cfg)  # the student's flow branch and propagation have nothing to learn from
    with pytest.raises(ValueError, match="input_size"):
        load_teacher(path, tiny_cfg.replace(num_frames=1, input_size=2 * tiny_cfg.input_size))


def test_a_run_with_a_teacher_ends_closer_to_its_heatmap_and_leaves_it_unchanged(
    tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path: Path
) -> None:
    path = _teacher_checkpoint(tmp_path / "teacher.pt", tiny_cfg)
    student = _narrow(tiny_cfg)
    teacher = load_teacher(path, student)
    before = {k: v.clone() for k, v in teacher.state_dict().items()}
    dataset = open_windows(tiny_root, "train", student)
    batch = Collator(student)([dataset[i] for i in range(min(4, len(dataset)))])
    train = TrainConfig(epochs=1, batch_size=2, seed=3, device="cpu", progress=False, val_every=0, lr=2e-3)
    gaps = {}
    for taught in (False, True):  # the same seed: the same start, the same steps but for the teacher's term
        trainer = Trainer(
            RunConfig(model=student, train=train), dataset, None, DistContext(), teacher=teacher if taught else None
        )
        terms = [trainer.train_step(batch) for _ in range(12)]
        assert (terms[0][LOSS_TERMS.index("distill")].item() > 0) == taught
        trainer.model.eval()
        with torch.no_grad():
            student_p = torch.sigmoid(trainer.model(batch.frames, batch.poses)["heatmap"])
            gaps[taught] = (student_p - torch.sigmoid(teacher(batch.frames, batch.poses))).abs().mean().item()
    assert gaps[True] < 0.7 * gaps[False], gaps
    assert all(torch.equal(before[k], v) for k, v in teacher.state_dict().items())
