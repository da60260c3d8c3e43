"""Heatmap distillation: a trained model (the teacher) gives a narrower one (the student) its heatmap as a soft target
beside the labels (`rafd train ... --teacher CKPT`, weight loss.distill_weight).

Why: a narrow network trained on the labels alone learns the simulated scenes about as well as the wide one, but not
necessarily where the wide one fires on the few real scans it was fine-tuned on; the teacher's heatmap carries that.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from rafd.config import SAME_INPUT_AND_TARGETS, RaFDConfig


def heatmap_distillation(student_logits: Tensor, teacher_logits: Tensor, num_positive: Tensor) -> Tensor:
    """Quality focal loss (Li et al., Generalized Focal Loss) towards the teacher's probabilities:
    student_logits, teacher_logits [B, 1, Hf, Wf], num_positive [] (the batch's labelled centres) -> scalar.

    Per cell -|t - p|^2 (t log p + (1 - t) log(1 - p)), p the student's probability, t the teacher's: the
    cross-entropy towards a soft target, down-weighted where the two already agree (most of the empty map), summed
    and divided by the labelled centres like the heatmap's focal loss, so the two terms have the same scale."""
    logits = student_logits.float()
    target = torch.sigmoid(teacher_logits.float())
    cross_entropy = F.binary_cross_entropy_with_logits(logits, target, reduction="none")  # [B, 1, Hf, Wf]
    agreement = (torch.sigmoid(logits) - target).abs().pow(2)
    return (agreement * cross_entropy).sum() / num_positive.clamp(min=1.0)


class Teacher(nn.Module):
    """A checkpoint's model frozen in eval mode, run at the student's frame count: frames [B, T, 1, S, S], poses
    [B, T, 3] -> heatmap logits [B, 1, Hf, Wf]. A multi-frame teacher of a single-frame student is its encoder and
    head (the part that was, or could have been, trained as a single-frame model)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model.eval().requires_grad_(False)

    def train(self, mode: bool = True) -> Teacher:  # always in eval mode: BatchNorm keeps its statistics
        return super().train(False)

    @torch.no_grad()
    def forward(self, frames: Tensor, poses: Tensor) -> Tensor:
        return self.model(frames, poses)["heatmap"]


def load_teacher(path: Path, student: RaFDConfig) -> Teacher:
    """The teacher for `student` from a checkpoint; ValueError when it cannot teach it (another input or targets, or
    fewer frames than the student, whose flow branch and propagation it would lack)."""
    from rafd.model import build_model
    from rafd.model.checkpoint import read_checkpoint

    state, cfg, _meta = read_checkpoint(path, map_location="cpu")
    for name in SAME_INPUT_AND_TARGETS:
        if getattr(cfg, name) != getattr(student, name):
            theirs, ours = getattr(cfg, name), getattr(student, name)
            raise ValueError(f"teacher {path}: its {name} {theirs!r} differs from the student's {ours!r}")
    if cfg.num_frames < student.num_frames:
        raise ValueError(f"teacher {path} sees {cfg.num_frames} frames, fewer than the student's {student.num_frames}")
    model = build_model(cfg.replace(num_frames=student.num_frames))
    missing = model.load_state_dict(state, strict=False).missing_keys
    if missing:  # every tensor of the teacher at the student's frame count must be trained
        raise ValueError(f"teacher {path} lacks {len(missing)} tensors of its model, e.g. {missing[0]}")
    return Teacher(model)
