"""The training loop: seeded, resumable, DDP-aware, mixed precision, with sharded validation and checkpoints.

Batches: `batch_size` is the GLOBAL number of windows per optimizer step (the paper's 8), split over the ranks and,
when one forward of batch_size / world_size windows is too big, over `micro_batch_size`-window micro-batches with
gradient accumulation (DDP's no_sync() skips the all-reduce of every micro-batch but the last). Losses are
normalised per micro-batch and averaged, as detection codebases do per GPU.

No host synchronisation per step: loss terms accumulate on the device and are read (averaged over ranks, checked
for NaN/inf) every `log_every` optimizer steps and at the end of an epoch.

Validation runs on every rank over its shard of the validation windows (rafd.train.distributed.shard_indices); the
results are gathered and summarised identically on every rank, so no rank waits alone in a barrier.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import random
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from rafd.config import SAME_INPUT_AND_TARGETS, RaFDConfig
from rafd.cpu import usable_cpus
from rafd.data.collate import Batch, Collator
from rafd.model.precision import autocast, check_precision, grad_scaler
from rafd.progress import bar as progress_bar
from rafd.train.config import RunConfig, TrainConfig
from rafd.train.distill import Teacher
from rafd.train.distributed import (
    DistContext,
    all_reduce_mean,
    barrier,
    broadcast_buffers,
    gather_objects,
    make_sampler,
    shard_indices,
    wrap_model,
)
from rafd.train.losses import LOSS_TERMS, RaFDLoss

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BatchPlan:
    micro_batch_size: int  # windows per rank per forward
    accumulation: int  # forwards per rank per optimizer step

    @property
    def per_rank(self) -> int:
        return self.micro_batch_size * self.accumulation


def plan_batches(batch_size: int, world_size: int, micro_batch_size: int | None = None) -> BatchPlan:
    """Split a global batch over ranks and accumulation steps; ValueError when it cannot be split evenly."""
    if batch_size % world_size:
        raise ValueError(
            f"the global batch of {batch_size} windows cannot be split evenly over {world_size} "
            f"processes: use a --batch-size that is a multiple of {world_size}"
        )
    per_rank = batch_size // world_size
    micro = per_rank if micro_batch_size is None else micro_batch_size
    if per_rank % micro:
        valid = [m for m in range(1, per_rank + 1) if per_rank % m == 0]
        raise ValueError(
            f"{per_rank} windows per process per step (batch {batch_size} / {world_size} processes) "
            f"cannot be made of micro-batches of {micro}; use --micro-batch-size in {valid}"
        )
    return BatchPlan(micro, per_rank // micro)


def default_workers(device: torch.device, local_world_size: int = 1) -> int:
    """DataLoader workers per rank: on CUDA up to 4 (one prepared-cache worker feeds ~100+ windows/s, see
    `rafd bench training loader`), leaving a CPU per rank for the training process; on the CPU none (the model
    needs the cores far more than the prepared windows do)."""
    if device.type != "cuda":
        return 0
    return max(1, min(4, usable_cpus() // max(1, local_world_size) - 1))


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
    """Trains one RaFD model; every rank validates its shard; rank 0 writes `out` (+ `.optim.pt`, `.history.json`)."""

    def __init__(
        self,
        config: RunConfig,
        train_set: Dataset,
        out: Path | None,
        ctx: DistContext,
        val_set: Dataset | None = None,
        run_meta: dict[str, Any] | None = None,
        teacher: Teacher | None = None,
    ) -> None:
        from rafd import build_model  # torch model code loads lazily

        if len(train_set) == 0:  # type: ignore[arg-type]
            raise ValueError("the training dataset holds no windows")
        model_cfg, train_cfg = config.model, config.train
        check_precision(train_cfg.precision, ctx.device)
        self.plan = plan_batches(train_cfg.batch_size, ctx.world_size, train_cfg.micro_batch_size)
        self.config = config  # recorded whole in every checkpoint (meta "run_config")
        self.model_cfg: RaFDConfig = model_cfg
        self.cfg: TrainConfig = train_cfg
        self.loss_cfg = config.loss
        self.ctx = ctx
        self.train_set = train_set
        self.val_set = val_set
        self.out = Path(out) if out is not None else None
        self.run_meta = dict(run_meta or {})  # recorded in the checkpoint beside the config (recipe, data, splits, ...)
        self.num_workers = (
            default_workers(ctx.device, ctx.local_world_size)
            if train_cfg.num_workers is None
            else train_cfg.num_workers
        )
        # The model is built under the run's seed: same seed -> same initial weights on every rank.
        seed_everything(train_cfg.seed)
        self.model = build_model(model_cfg).to(ctx.device)
        for name in train_cfg.freeze:
            part = getattr(self.model, name)
            if part is None:
                raise ValueError(f"freeze: this {model_cfg.num_frames}-frame model has no {name}")
            part.requires_grad_(False)  # before build_optimizer, which takes only parameters that train
        self.loss = RaFDLoss(self.loss_cfg)
        # a frozen model whose heatmap is a soft target beside the labels (rafd.train.distill); not in the checkpoint
        self.teacher = teacher.to(ctx.device) if teacher is not None else None
        self.optimizer = build_optimizer(self.model, train_cfg)
        self.ddp_model = wrap_model(self.model, ctx)  # converts BatchNorm in place under DDP on CUDA
        self.scaler = grad_scaler(ctx.device, train_cfg.precision)
        self.collate = Collator(model_cfg)
        self.sampler = make_sampler(train_set, ctx, seed=train_cfg.seed, shuffle=True)
        self.loader = DataLoader(
            self.train_set,
            batch_size=self.plan.micro_batch_size,
            sampler=self.sampler,
            num_workers=self.num_workers,
            collate_fn=self.collate,
            worker_init_fn=_worker_init,
            generator=torch.Generator().manual_seed(train_cfg.seed),
            pin_memory=ctx.device.type == "cuda",
            persistent_workers=self.num_workers > 0,
            prefetch_factor=4 if self.num_workers > 0 else None,
            drop_last=False,
        )
        self.epoch = 0  # epochs completed
        self.step = 0  # optimizer steps completed
        self.history: list[dict[str, Any]] = []

    # ----------------------------------------------------------------- data
    def steps_per_epoch(self) -> int:
        micro_batches = math.ceil(len(self.sampler) / self.plan.micro_batch_size)
        steps = math.ceil(micro_batches / self.plan.accumulation)
        if self.cfg.max_steps_per_epoch is not None:
            steps = min(steps, self.cfg.max_steps_per_epoch)
        return steps

    def _groups(self, batches: Iterable[Batch]) -> Iterator[list[Batch]]:
        """Micro-batches -> lists of `accumulation` micro-batches (the last list of an epoch may be shorter)."""
        group: list[Batch] = []
        for batch in batches:
            group.append(batch)
            if len(group) == self.plan.accumulation:
                yield group
                group = []
        if group:
            yield group

    # ----------------------------------------------------------------- steps
    def train_step(self, batches: Batch | list[Batch]) -> torch.Tensor:
        """One optimizer step over micro-batches -> the loss terms (LOSS_TERMS order) on the device, unsynchronised."""
        group = [batches] if isinstance(batches, Batch) else list(batches)
        self.ddp_model.train()
        for name in self.cfg.freeze:
            getattr(self.model, name).eval()  # frozen parts keep their BatchNorm running statistics
        total_steps = self.cfg.epochs * self.steps_per_epoch()
        for param_group in self.optimizer.param_groups:
            param_group["lr"] = learning_rate(self.cfg, self.step, total_steps)
        self.optimizer.zero_grad(set_to_none=True)
        terms_sum = torch.zeros(len(LOSS_TERMS), device=self.ctx.device)
        for index, batch in enumerate(group):
            batch = batch.to(self.ctx.device)
            last = index == len(group) - 1
            # Gradients of all but the last micro-batch stay local: one all-reduce per optimizer step.
            # (ctx.enabled: wrap_model gave a DistributedDataParallel)
            sync = (
                contextlib.nullcontext()
                if last or not self.ctx.enabled
                else cast(nn.parallel.DistributedDataParallel, self.ddp_model).no_sync()
            )
            with sync:
                targets = batch.targets
                with autocast(self.ctx.device, self.cfg.precision):
                    if self.teacher is not None:
                        targets = {**targets, "teacher_heatmap": self.teacher(batch.frames, batch.poses)}
                    outputs = self.ddp_model(
                        batch.frames,
                        batch.poses,
                        gt_indices=batch.targets["centre_index"],
                        gt_mask=batch.targets["box_mask"],
                    )
                terms = self.loss(outputs, targets)  # float32 whatever the autocast precision
                self.scaler.scale(terms["total"] / len(group)).backward()
            terms_sum += torch.stack([terms[key].detach().float() for key in LOSS_TERMS])
        if self.cfg.grad_clip > 0:
            self.scaler.unscale_(self.optimizer)
            nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        self.scaler.step(self.optimizer)  # skips the step when fp16 gradients overflowed
        self.scaler.update()
        self.step += 1
        return terms_sum / len(group)

    def _synchronised(self, terms: torch.Tensor, count: int) -> dict[str, float]:
        """Mean of `count` steps' summed terms over ranks -> floats; FloatingPointError on NaN / inf."""
        values = all_reduce_mean(terms / max(count, 1), self.ctx).tolist()
        record = dict(zip(LOSS_TERMS, values))
        if not all(math.isfinite(v) for v in values):
            raise FloatingPointError(f"non-finite loss by step {self.step}: {record}")
        return record

    def train_epoch(self) -> dict[str, Any]:
        """One epoch -> mean loss terms, a loss curve every `log_every` steps, and throughput."""
        epoch = self.epoch
        seed_everything(epoch_seed(self.cfg.seed, epoch))
        self.sampler.set_epoch(epoch)  # before iter(): the keys carry the epoch
        steps = self.steps_per_epoch()
        epoch_sum = torch.zeros(len(LOSS_TERMS), device=self.ctx.device)
        interval_sum = torch.zeros_like(epoch_sum)
        interval, curve, windows = 0, [], 0
        start = time.perf_counter()
        bar = progress_bar(
            total=steps,
            desc=f"train epoch {epoch + 1}/{self.cfg.epochs}",
            unit="step",
            enabled=self.cfg.progress and self.ctx.is_main,
        )
        for index, group in enumerate(self._groups(self.loader)):
            if index >= steps:
                break
            terms = self.train_step(group)
            epoch_sum += terms
            interval_sum += terms
            interval += 1
            windows += sum(len(b) for b in group) * self.ctx.world_size
            bar.update(1)
            if interval == self.cfg.log_every or index == steps - 1:
                point = self._synchronised(interval_sum, interval)
                curve.append({"step": self.step, **{f"loss_{k}": v for k, v in point.items()}})
                bar.set_postfix({k: f"{point[k]:.3f}" for k in ("total", "heatmap", "size", "rotation", "flow")})
                interval_sum.zero_()
                interval = 0
        bar.close()
        broadcast_buffers(self.model, self.ctx)
        elapsed = time.perf_counter() - start
        record: dict[str, Any] = {f"loss_{k}": v for k, v in self._synchronised(epoch_sum, steps).items()}
        record.update(windows=windows, seconds=elapsed, windows_per_second=windows / max(elapsed, 1e-9), curve=curve)
        return record

    # ----------------------------------------------------------------- loop
    def fit(self) -> list[dict[str, Any]]:
        """Train from self.epoch to cfg.epochs; validate (all ranks) and checkpoint (rank 0) after every epoch."""
        while self.epoch < self.cfg.epochs:
            record: dict[str, Any] = {"epoch": self.epoch + 1}
            record.update(self.train_epoch())
            self.epoch += 1
            record["step"] = self.step
            if self._should_validate():
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
        """mAP@0.3/0.5/0.7 and EPE on the validation set: each rank predicts its shard, all ranks summarise."""
        from rafd.data.windows import WindowSubset
        from rafd.eval.predict import predict, summarise

        assert self.val_set is not None
        shard = shard_indices(len(self.val_set), self.ctx)  # type: ignore[arg-type]
        results = predict(
            self.model,
            WindowSubset(self.val_set, shard),
            self.model_cfg,
            self.ctx.device,
            batch_size=self.plan.micro_batch_size,
            progress=False,
            precision=self.cfg.precision,
            num_workers=self.num_workers,
        )
        gathered = sorted(gather_objects(list(zip(shard, results)), self.ctx), key=lambda pair: pair[0])
        summary = summarise([result for _, result in gathered])
        return {f"val_{k}": v for k, v in summary.items() if isinstance(v, (int, float))}

    # ----------------------------------------------------------------- checkpoints
    def save(self, path: Path) -> None:
        """Model checkpoint via rafd.save_checkpoint + `<path>.optim.pt` + `<path>.history.json`."""
        from rafd.model.checkpoint import save_checkpoint

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            **self.run_meta,
            "epoch": self.epoch,
            "step": self.step,
            "run_config": self.config.to_dict(),
            "world_size": self.ctx.world_size,
            "batch_plan": dataclasses.asdict(self.plan),
            "metrics": {
                k: v for k, v in (self.history[-1] if self.history else {}).items() if isinstance(v, (int, float))
            },
        }
        save_checkpoint(path, self.model, self.model_cfg, meta=meta)
        state = {
            "optimizer": self.optimizer.state_dict(),
            "scaler": self.scaler.state_dict(),
            "epoch": self.epoch,
            "step": self.step,
            "seed": self.cfg.seed,
            "world_size": self.ctx.world_size,
            "freeze": list(self.cfg.freeze),  # the optimizer holds only the parts that train
        }
        torch.save(state, optimizer_state_path(path))
        history_path(path).write_text(json.dumps(self.history, indent=2))

    def initialise_from(self, path: Path) -> dict[str, list[str]]:
        """Start from another checkpoint's weights (a two-stage recipe: a single-frame model's encoder and head under a
        multi-frame run). Every tensor whose name and shape match is copied; the rest (a single-frame model has no flow
        branch or propagation) keep this run's initialisation. Optimizer, epoch and history start fresh.
        The two models must read the same input (size, resolution, normalisation) and predict the same targets:
        otherwise the copied encoder would see other pixels, the copied head other boxes, than they learned."""
        from rafd.model.checkpoint import read_checkpoint

        state, source_cfg, _meta = read_checkpoint(Path(path), map_location="cpu")
        for field in SAME_INPUT_AND_TARGETS:
            if getattr(source_cfg, field) != getattr(self.model_cfg, field):
                raise ValueError(
                    f"cannot initialise from {path}: its {field} {getattr(source_cfg, field)!r} differs "
                    f"from this run's {getattr(self.model_cfg, field)!r}"
                )
        target = self.model.state_dict()
        copied = {k: v for k, v in state.items() if k in target and target[k].shape == v.shape}
        report = {
            "copied": sorted(copied),
            "skipped": sorted(k for k in state if k not in copied),  # absent here or another shape
            "fresh": sorted(k for k in target if k not in copied),
        }
        if not copied:
            raise ValueError(f"cannot initialise from {path}: no tensor of it fits this model")
        self.model.load_state_dict(copied, strict=False)
        self.run_meta["init"] = str(path)
        log.info(
            "initialised %d of %d tensors from %s (%d of its tensors skipped; %d fresh here, e.g. %s)",
            len(copied),
            len(target),
            path,
            len(report["skipped"]),
            len(report["fresh"]),
            ", ".join(sorted({k.split(".")[0] for k in report["fresh"]})) or "none",
        )
        return report

    def resume(self, path: Path) -> None:
        """Continue from a checkpoint written by save(): weights, optimizer, scaler, epoch/step, history."""
        from rafd.model.checkpoint import load_checkpoint

        path = Path(path)
        state_path = optimizer_state_path(path)
        if not state_path.is_file():
            raise FileNotFoundError(f"cannot resume: {state_path} (optimizer state written beside {path}) is missing")
        model, cfg, meta = load_checkpoint(path, map_location="cpu")
        if cfg != self.model_cfg:
            raise ValueError(f"cannot resume {path}: its model config differs from this run's")
        state = torch.load(state_path, map_location=self.ctx.device, weights_only=True)
        if int(state["seed"]) != self.cfg.seed:
            log.warning("resuming %s trained with seed %s under seed %s", path, state["seed"], self.cfg.seed)
        saved_freeze = sorted(state.get("freeze", []))
        if saved_freeze != sorted(self.cfg.freeze):
            # the optimizer state holds one entry per parameter that trained: another split cannot be restored
            raise ValueError(
                f"cannot resume {path}: it was trained freezing {' '.join(saved_freeze) or 'nothing'}, "
                f"this run freezes {' '.join(sorted(self.cfg.freeze)) or 'nothing'}; resume with the same "
                "--freeze"
            )
        self.model.load_state_dict(model.state_dict())
        if int(state.get("world_size", self.ctx.world_size)) != self.ctx.world_size:
            log.warning(
                "resuming %s trained on %s processes on %d: the data order differs from an uninterrupted run",
                path,
                state["world_size"],
                self.ctx.world_size,
            )
        self.optimizer.load_state_dict(state["optimizer"])
        if "scaler" in state:
            self.scaler.load_state_dict(state["scaler"])
        self.epoch = int(state["epoch"])
        self.step = int(state["step"])
        hist = history_path(path)
        self.history = json.loads(hist.read_text()) if hist.is_file() else []
        # the run's provenance goes on (a two-stage run's start); an operating threshold does not: the weights move
        if (meta or {}).get("init") is not None:
            self.run_meta.setdefault("init", meta["init"])
        log.info("resumed %s at epoch %d, step %d", path, self.epoch, self.step)


def _format_record(record: dict[str, Any]) -> str:
    return " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items() if k != "curve")
