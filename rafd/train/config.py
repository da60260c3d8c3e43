"""The one typed config of a training run: the network, its data and augmentation, the loss and the training, one
tree of frozen dataclasses (torch-free) with the defaults written once, here and in rafd.config (the network's).

    RunConfig
      model: RaFDConfig    the network (rafd.config; what checkpoints and ONNX metadata store as "config")
      data:  DataConfig    how the windows are drawn: augmentation (data.augment.*, data.mix_augment.*), limits
      loss:  LossConfig    the weights of the loss terms (loss.flow_weight=0: the no-flow-supervision ablation)
      train: TrainConfig   the optimisation and how it runs (train.lr, train.precision, train.freeze, ...)

Every field is set on the command line by its dotted key (`rafd train ROOT ... train.lr=1e-3
model.flow.local_radius=2`; rafd.config_tree), a named recipe is a list of such settings (rafd.train.recipes), and
the checkpoint stores the whole tree (meta "run_config"), so a run is known by what it was, not by its flags. The
defaults are the paper's: RunConfig() is the `paper` recipe.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

from rafd.config import FREEZABLE, RaFDConfig
from rafd.config_tree import from_dict, overridden, to_dict
from rafd.data.augment import AugmentConfig

OPTIMIZERS = ("adamw", "adam")
SCHEDULES = ("constant", "cosine")
DEFAULT_TIMEOUT_MINUTES = 30.0  # a collective (DDP) waiting longer fails instead of hanging


@dataclass(frozen=True)
class DataConfig:
    """How the training windows are drawn. Where they are read from (the data root, its splits and scan cache, the
    validation and mixed-in roots) is the run's, not the config's: rafd.train.run.TrainRun."""

    # The training root's windows: turned, mirrored, their intensities changed, cut away from the radar
    # (rafd.data.augment). The paper states no augmentation.
    augment: AugmentConfig = field(default_factory=lambda: AugmentConfig(enabled=False))
    # The mixed-in root's windows (--mix-data). A recipe gives them its own augmentation (rafd.train.recipes), so a
    # run's changes of data.augment (e.g. tile shifts kept inside a few real scans' labelled area) leave the replayed
    # simulation augmented as it was trained.
    mix_augment: AugmentConfig = field(default_factory=lambda: AugmentConfig(enabled=False))
    mix_share: float = 0.5  # of each epoch's windows from the mixed-in root, in (0, 1); a half: as many as ROOT's
    max_windows: int | None = None  # at most N (evenly spaced) training windows; None: all
    max_val_windows: int | None = None  # at most N validation windows; None: all
    # Also each sequence's first T-1 frames, in windows padded as the service pads a new stream's (a short real
    # sequence keeps all its labelled frames); without it only full windows, the paper's protocol.
    warm_up_windows: bool = False
    estimate_poses: bool = False  # radar odometry for sequences without ego_poses.csv (slow; prefer rafd odometry)

    def __post_init__(self) -> None:
        if not 0.0 < self.mix_share < 1.0:
            raise ValueError(f"data.mix_share is a share of each epoch's windows, in (0, 1); got {self.mix_share}")


@dataclass(frozen=True)
class LossConfig:
    # Weights of the detection terms (CenterNet/CenterFormer use 1 for the heatmap and the offsets).
    heatmap_weight: float = 1.0
    offset_weight: float = 1.0
    size_weight: float = 1.0
    rotation_weight: float = 1.0
    # Weight of the flow term; 0 is the "without flow supervision" ablation (paper: L = L_det + L_flow).
    flow_weight: float = 1.0
    # Weight of the heatmap distillation term of a run with a teacher (`rafd train --teacher CKPT`; rafd.train.distill).
    distill_weight: float = 1.0
    # CornerNet focal loss exponents: alpha on (1 - p) / p, beta on (1 - Gaussian) for negatives.
    focal_alpha: float = 2.0
    focal_beta: float = 4.0


@dataclass(frozen=True)
class TrainConfig:
    """The optimisation and how it runs."""

    epochs: int = 10  # paper: 10 epochs
    batch_size: int = 8  # GLOBAL windows per optimizer step, over all ranks and accumulation steps; paper: 8
    micro_batch_size: int | None = None  # windows per rank per forward; None = batch_size / world_size
    lr: float = 2e-4  # paper
    weight_decay: float = 1e-2  # paper
    # "adam": torch.optim.Adam with L2 weight decay, as the paper says ("the Adam", wd 1e-2).
    # "adamw": decoupled weight decay (what CenterFormer's det3d "adam" with fixed_wd=True does).
    optimizer: str = "adam"
    lr_schedule: str = "constant"  # the paper states no schedule; "cosine" decays per step to 0
    grad_clip: float = 35.0  # max gradient norm (CenterFormer's 35); 0 disables
    seed: int = 0  # of the weights, the data order and the augmentation
    device: str = "auto"  # torch device: cpu | cuda | cuda:N | auto
    # fp32 | bf16 (autocast: several times faster on CPUs with avx512_bf16/AMX and on GPUs) | fp16 (autocast +
    # gradient scaler; CUDA)
    precision: str = "fp32"
    threads: int | None = None  # torch's CPU threads per process; None = the usable CPUs / the local processes
    num_workers: int | None = None  # DataLoader workers per rank; None = rafd.train.trainer.default_workers(device)
    val_every: int = 1  # validate every N epochs (needs a validation set); 0 disables
    max_steps_per_epoch: int | None = None  # cap (smoke runs); None = the whole epoch
    log_every: int = 20  # optimizer steps between host synchronisations (loss log, NaN check)
    dist_timeout_minutes: float = DEFAULT_TIMEOUT_MINUTES
    progress: bool = True  # tqdm bar on rank 0 (--quiet silences every bar)
    # Parts of the network that do not train (FREEZABLE): weights fixed and BatchNorm statistics kept, e.g. a
    # single-frame model's encoder under a two-stage 4-frame run, so the second stage learns only what the past adds.
    freeze: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.lr_schedule not in SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {SCHEDULES}, got {self.lr_schedule!r}")
        if self.epochs < 1 or self.batch_size < 1 or (self.micro_batch_size is not None and self.micro_batch_size < 1):
            raise ValueError("epochs, batch_size and micro_batch_size must be >= 1")
        if self.log_every < 1:
            raise ValueError("log_every must be >= 1")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        unknown = sorted(set(self.freeze) - set(FREEZABLE))
        if unknown:
            raise ValueError(f"freeze: {unknown} are not parts of the network; choose from {FREEZABLE}")


@dataclass(frozen=True)
class RunConfig:
    """Everything a training run sets (the module docstring)."""

    model: RaFDConfig = field(default_factory=RaFDConfig)
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def overridden(self, changes: dict[str, Any]) -> RunConfig:
        """This config with the fields named by dotted keys changed (text parsed by the field's type)."""
        return overridden(self, changes)

    def replace(self, **changes: Any) -> RunConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return to_dict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunConfig:
        """Rebuild from `to_dict()` (a checkpoint's meta "run_config"); unknown or missing keys are an error."""
        return from_dict(cls, data)
