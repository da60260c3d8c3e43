"""The training loop: seeded, resumable, DDP-aware, with periodic validation mAP and checkpoints."""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from rafd.config import RaFDConfig
from rafd.train.collate import Batch, Collator
from rafd.train.distributed import (
    DistContext,
    all_reduce_mean,
    barrier,
    broadcast_buffers,
    make_sampler,
    unwrap_model,
    wrap_model,
)
from rafd.train.losses import LossConfig, RaFDLoss

log = logging.getLogger(__name__)

OPTIMIZERS = ("adamw", "adam")
SCHEDULES = ("constant", "cosine")


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 10  # paper: 10 epochs
    batch_size: int = 8  # per process; paper: 8
    lr: float = 2e-4  # paper
    weight_decay: float = 1e-2  # paper
    # "adamw": decoupled weight decay. The paper says "Adam, wd 1e-2"; CenterFormer (its base) trains
    # with det3d's adam + fixed_wd=True, which IS decoupled decay, so AdamW is the faithful reading.
    # "adam": torch.optim.Adam with L2 weight_decay (coupled), for comparison.
    optimizer: str = "adamw"
    lr_schedule: str = "constant"  # the paper states no schedule; "cosine" decays per step to 0
    grad_clip: float = 35.0  # max gradient norm (CenterFormer's 35); 0 disables
    seed: int = 0
    device: str = "auto"
    num_workers: int = 0  # DataLoader workers; 0 keeps tests and the 2-core CPU simple
    val_every: int = 1  # validate every N epochs (needs a validation set); 0 disables
    max_steps_per_epoch: int | None = None  # cap (smoke runs); None = the whole epoch
    progress: bool = True  # tqdm bar on rank 0

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.lr_schedule not in SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {SCHEDULES}, got {self.lr_schedule!r}")
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError("epochs and batch_size must be >= 1")


def optimizer_state_path(checkpoint: Path) -> Path:
    """Optimizer/progress state lives beside the model checkpoint: `<ckpt>.optim.pt` (weights_only-safe)."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name + ".optim.pt")


def history_path(checkpoint: Path) -> Path:
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name + ".history.json")


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def epoch_seed(seed: int, epoch: int) -> int:
    """Each epoch reseeds every RNG from (seed, epoch), so a run resumed at an epoch boundary is exact."""
    return int(np.random.SeedSequence([seed, epoch]).generate_state(1)[0])


def _worker_init(worker_id: int) -> None:
    # DataLoader seeds torch per worker from its generator; derive numpy/python from that seed.
    worker_seed = torch.initial_seed() % 2**32
    np.random.seed(worker_seed)
    random.seed(worker_seed)


def build_optimizer(model: nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    params = [p for p in model.parameters() if p.requires_grad]
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay)


def learning_rate(cfg: TrainConfig, step: int, total_steps: int) -> float:
    """Stateless schedule (a function of the global step), so resuming needs no scheduler state."""
    if cfg.lr_schedule == "constant" or total_steps <= 0:
        return cfg.lr
    return 0.5 * cfg.lr * (1.0 + math.cos(math.pi * min(step, total_steps) / total_steps))


class Trainer:
    """Trains one RaFD model; rank 0 validates and writes `out` (+ `.optim.pt`, `.history.json`)."""

    def __init__(
        self,
        model_cfg: RaFDConfig,
        train_cfg: TrainConfig,
        train_set: Dataset,
        out: Path | None,
        ctx: DistContext,
        loss_cfg: LossConfig | None = None,
        val_set: Dataset | None = None,
    ) -> None:
        from rafd import build_model  # torch model code loads lazily

        if len(train_set) == 0:  # type: ignore[arg-type]
            raise ValueError("the training dataset holds no windows")
        self.model_cfg = model_cfg
        self.cfg = train_cfg
        self.loss_cfg = loss_cfg or LossConfig()
        self.ctx = ctx
        self.train_set = train_set
        self.val_set = val_set
        self.out = Path(out) if out is not None else None
        # The model is built under the run's seed: same seed -> same initial weights on every rank.
        seed_everything(train_cfg.seed)
        self.model = build_model(model_cfg).to(ctx.device)
        self.loss = RaFDLoss(self.loss_cfg)
        self.optimizer = build_optimizer(self.model, train_cfg)
        self.ddp_model = wrap_model(self.model, ctx)
        self.collate = Collator(model_cfg)
        self.sampler = make_sampler(train_set, ctx, seed=train_cfg.seed, shuffle=True)
        self.epoch = 0  # epochs completed
        self.step = 0  # optimizer steps completed
        self.history: list[dict[str, Any]] = []

    # ----------------------------------------------------------------- data
    def steps_per_epoch(self) -> int:
        steps = math.ceil(len(self.sampler) / self.cfg.batch_size)
        if self.cfg.max_steps_per_epoch is not None:
            steps = min(steps, self.cfg.max_steps_per_epoch)
        return steps

    def _loader(self, epoch: int) -> DataLoader:
        self.sampler.set_epoch(epoch)
        generator = torch.Generator().manual_seed(epoch_seed(self.cfg.seed, epoch))
        return DataLoader(
            self.train_set,
            batch_size=self.cfg.batch_size,
            sampler=self.sampler,
            num_workers=self.cfg.num_workers,
            collate_fn=self.collate,
            worker_init_fn=_worker_init,
            generator=generator,
            pin_memory=self.ctx.device.type == "cuda",
            drop_last=False,
        )

    # ----------------------------------------------------------------- steps
    def train_step(self, batch: Batch) -> dict[str, float]:
        """One optimizer step on a batch -> the (rank-averaged) loss terms as floats."""
        self.ddp_model.train()
        batch = batch.to(self.ctx.device)
        total_steps = self.cfg.epochs * self.steps_per_epoch()
        for group in self.optimizer.param_groups:
            group["lr"] = learning_rate(self.cfg, self.step, total_steps)
        outputs = self.ddp_model(
            batch.frames, batch.poses, gt_indices=batch.targets["centre_index"], gt_mask=batch.targets["box_mask"]
        )
        terms = self.loss(outputs, batch.targets)
        if not torch.isfinite(terms["total"]):
            raise FloatingPointError(f"non-finite loss at step {self.step}: { {k: v.item() for k, v in terms.items()} }")
        self.optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        if self.cfg.grad_clip > 0:
            nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        self.optimizer.step()
        self.step += 1
        stacked = torch.stack([v.detach().float() for v in terms.values()])
        stacked = all_reduce_mean(stacked, self.ctx)
        return dict(zip(terms.keys(), stacked.tolist()))

    def train_epoch(self) -> dict[str, float]:
        """One epoch (RNGs reseeded from (seed, epoch)) -> mean loss terms and throughput."""
        epoch = self.epoch
        seed_everything(epoch_seed(self.cfg.seed, epoch))
        steps = self.steps_per_epoch()
        sums: dict[str, float] = {}
        windows = 0
        start = time.perf_counter()
        bar = tqdm(
            total=steps,
            desc=f"epoch {epoch + 1}/{self.cfg.epochs}",
            disable=not (self.cfg.progress and self.ctx.is_main),
            dynamic_ncols=True,
        )
        for index, batch in enumerate(self._loader(epoch)):
            if index >= steps:
                break
            terms = self.train_step(batch)
            windows += len(batch) * self.ctx.world_size
            for key, value in terms.items():
                sums[key] = sums.get(key, 0.0) + value
            bar.update(1)
            bar.set_postfix({k: f"{terms[k]:.3f}" for k in ("total", "heatmap", "offset", "size", "rotation", "flow")})
        bar.close()
        broadcast_buffers(self.model, self.ctx)
        elapsed = time.perf_counter() - start
        record = {f"loss_{k}": v / max(steps, 1) for k, v in sums.items()}
        record.update(windows=windows, seconds=elapsed, windows_per_second=windows / max(elapsed, 1e-9))
        return record

    # ----------------------------------------------------------------- loop
    def fit(self) -> list[dict[str, Any]]:
        """Train from self.epoch to cfg.epochs; rank 0 validates and checkpoints after every epoch."""
        while self.epoch < self.cfg.epochs:
            record: dict[str, Any] = {"epoch": self.epoch + 1}
            record.update(self.train_epoch())
            self.epoch += 1
            record["step"] = self.step
            if self.ctx.is_main and self._should_validate():
                record.update(self.validate())
            self.history.append(record)
            if self.ctx.is_main:
                log.info("epoch %d: %s", self.epoch, _format_record(record))
                if self.out is not None:
                    self.save(self.out)
            barrier(self.ctx)
        return self.history

    def _should_validate(self) -> bool:
        if self.val_set is None or self.cfg.val_every <= 0:
            return False
        return self.epoch % self.cfg.val_every == 0 or self.epoch == self.cfg.epochs

    def validate(self) -> dict[str, float]:
        """mAP@0.3/0.5/0.7 and EPE of the current weights on the validation set."""
        from rafd.train.predict import predict, summarise

        results = predict(
            self.model, self.val_set, self.model_cfg, self.ctx.device, batch_size=self.cfg.batch_size, progress=False
        )
        return {f"val_{k}": v for k, v in summarise(results).items() if isinstance(v, (int, float))}

    # ----------------------------------------------------------------- checkpoints
    def save(self, path: Path) -> None:
        """Model checkpoint via rafd.save_checkpoint + `<path>.optim.pt` + `<path>.history.json`."""
        from rafd.checkpoint import save_checkpoint

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "epoch": self.epoch,
            "step": self.step,
            "train_config": dataclasses.asdict(self.cfg),
            "loss_config": dataclasses.asdict(self.loss_cfg),
            "metrics": {k: v for k, v in (self.history[-1] if self.history else {}).items() if isinstance(v, (int, float))},
        }
        save_checkpoint(path, self.model, self.model_cfg, meta=meta)
        state = {
            "optimizer": self.optimizer.state_dict(),
            "epoch": self.epoch,
            "step": self.step,
            "seed": self.cfg.seed,
            "world_size": self.ctx.world_size,
        }
        torch.save(state, optimizer_state_path(path))
        history_path(path).write_text(json.dumps(self.history, indent=2))

    def resume(self, path: Path) -> None:
        """Continue from a checkpoint written by save(): weights, optimizer, epoch/step, history."""
        from rafd.checkpoint import load_checkpoint

        path = Path(path)
        state_path = optimizer_state_path(path)
        if not state_path.is_file():
            raise FileNotFoundError(f"cannot resume: {state_path} (optimizer state written beside {path}) is missing")
        model, cfg, _meta = load_checkpoint(path, map_location="cpu")
        if cfg != self.model_cfg:
            raise ValueError(f"cannot resume {path}: its model config differs from this run's")
        self.model.load_state_dict(model.state_dict())
        state = torch.load(state_path, map_location=self.ctx.device, weights_only=True)
        if int(state["seed"]) != self.cfg.seed:
            log.warning("resuming %s trained with seed %s under seed %s", path, state["seed"], self.cfg.seed)
        self.optimizer.load_state_dict(state["optimizer"])
        self.epoch = int(state["epoch"])
        self.step = int(state["step"])
        hist = history_path(path)
        self.history = json.loads(hist.read_text()) if hist.is_file() else []
        log.info("resumed %s at epoch %d, step %d", path, self.epoch, self.step)


def _format_record(record: dict[str, Any]) -> str:
    return " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items())
