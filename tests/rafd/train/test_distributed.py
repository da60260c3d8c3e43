"""Two CPU processes (gloo) with torchrun's environment: lock-step training, global batch = ranks x accumulation,
sharded validation equal to one process's, and torchrun driving rafd-train end to end."""

from __future__ import annotations

import dataclasses
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from rafd.config import RaFDConfig
from rafd.data.windows import open_windows
from rafd.train.config import RunConfig, TrainConfig
from rafd.train.distributed import DistContext, cleanup_distributed, init_distributed, shard_indices, wrap_model
from rafd.train.trainer import Trainer, plan_batches

# One optimizer step over a global batch of 4 windows, micro-batches of 1 (BatchNorm sees the same batches).
STEP = dict(
    epochs=1, batch_size=4, micro_batch_size=1, seed=5, device="cpu", progress=False, max_steps_per_epoch=1, val_every=1
)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _run(root: str, cfg_json: str, out: Path, ctx: DistContext, tag: str) -> None:
    """One optimizer step (parameters saved), then validation of the reference weights (the same on every rank)."""
    cfg = RaFDConfig.from_json(cfg_json)
    dataset = open_windows(root, "train", cfg)
    trainer = Trainer(RunConfig(model=cfg, train=TrainConfig(**STEP)), dataset, out / f"{tag}.pt", ctx, val_set=dataset)
    trainer.fit()
    params = {name: p.detach().clone() for name, p in trainer.model.named_parameters()}
    trainer.model.load_state_dict(torch.load(out / "reference.pt", weights_only=True))
    torch.save({"params": params, "val": trainer.validate()}, out / f"{tag}_rank{ctx.rank}.pt")


def _worker(rank: int, world_size: int, port: int, root: str, cfg_json: str, out: str) -> None:
    # The variables torchrun sets for each process.
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE=str(world_size),
        LOCAL_RANK=str(rank),
        LOCAL_WORLD_SIZE=str(world_size),
    )
    torch.set_num_threads(1)
    ctx = init_distributed("cpu", timeout_minutes=5)
    try:
        _run(root, cfg_json, Path(out), ctx, "ddp")
    finally:
        cleanup_distributed()


@pytest.fixture(scope="module")
def runs(tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ddp")
    # Reference weights for validation: a few steps of training, so the detections are not trivial.
    cfg = RaFDConfig.from_json(tiny_cfg.to_json())
    reference = Trainer(
        RunConfig(model=cfg, train=TrainConfig(**{**STEP, "max_steps_per_epoch": 4, "lr": 3e-3})),
        open_windows(tiny_root, "train", cfg),
        None,
        DistContext(),
    )
    reference.fit()
    torch.save(reference.model.state_dict(), out / "reference.pt")
    mp.spawn(_worker, args=(2, _free_port(), str(tiny_root), tiny_cfg.to_json(), str(out)), nprocs=2, join=True)
    _run(str(tiny_root), tiny_cfg.to_json(), out, DistContext(), "single")  # 1 process, accumulation 4
    return out


@pytest.mark.slow
def test_two_ranks_with_accumulation_equal_one_process_with_the_same_global_batch(runs: Path) -> None:
    rank0, rank1, single = (
        torch.load(runs / f"{t}.pt", weights_only=True)["params"] for t in ("ddp_rank0", "ddp_rank1", "single_rank0")
    )
    for name in rank0:
        assert torch.equal(rank0[name], rank1[name]), f"{name} differs between ranks"
        # 2 ranks x 2 micro-batches and 1 rank x 4 micro-batches average the same 4 windows' gradients
        torch.testing.assert_close(rank0[name], single[name], rtol=1e-4, atol=1e-6, msg=f"{name}")
    assert (runs / "ddp.pt").is_file()  # rank 0 wrote the checkpoint


def test_sharded_validation_equals_single_process_validation(runs: Path) -> None:
    rank0, rank1, single = (
        torch.load(runs / f"{t}.pt", weights_only=True)["val"] for t in ("ddp_rank0", "ddp_rank1", "single_rank0")
    )
    assert rank0 == rank1 and set(rank0) >= {"val_mAP@0.5", "val_epe_all", "val_frames"}
    assert rank0["val_frames"] == single["val_frames"] and single["val_mAP@0.3"] > 0
    for key in rank0:
        assert rank0[key] == pytest.approx(single[key], rel=1e-4, abs=1e-6, nan_ok=True), key


def test_shards_cover_every_window_once() -> None:
    shards = [shard_indices(11, DistContext(rank=r, world_size=3)) for r in range(3)]
    assert sorted(i for shard in shards for i in shard) == list(range(11))


@pytest.mark.parametrize(
    "batch, world, micro, expected", [(8, 8, None, (1, 1)), (8, 1, None, (8, 1)), (8, 2, 1, (1, 4)), (8, 1, 2, (2, 4))]
)
def test_global_batch_plans(batch, world, micro, expected) -> None:
    plan = plan_batches(batch, world, micro)
    assert (plan.micro_batch_size, plan.accumulation) == expected
    assert plan.per_rank * world == batch


def test_batches_that_cannot_be_split_are_clear_errors() -> None:
    with pytest.raises(ValueError, match="multiple of 3"):
        plan_batches(8, 3)
    with pytest.raises(ValueError, match=r"micro-batch-size in \[1, 2, 4\]"):
        plan_batches(8, 2, 3)


def test_sync_batchnorm_only_under_ddp_on_cuda_and_checkpoints_keep_their_keys(tiny_cfg: RaFDConfig) -> None:
    """The CUDA path converts BatchNorm to SyncBatchNorm (torch runs it on GPUs only): check the conversion and that
    a converted model's state dict loads into the plain model a checkpoint rebuilds."""
    from rafd import build_model
    from rafd.train.distributed import uses_sync_batchnorm

    assert not uses_sync_batchnorm(DistContext(world_size=2, device=torch.device("cpu")))
    assert not uses_sync_batchnorm(DistContext(world_size=1, device=torch.device("cuda", 0)))
    assert uses_sync_batchnorm(DistContext(world_size=2, device=torch.device("cuda", 0)))
    model = build_model(tiny_cfg)
    converted = torch.nn.SyncBatchNorm.convert_sync_batchnorm(build_model(tiny_cfg))
    assert any(isinstance(m, torch.nn.SyncBatchNorm) for m in converted.modules())
    model.load_state_dict(converted.state_dict(), strict=True)
    assert wrap_model(model, DistContext()) is model  # one process: no wrapper


@pytest.mark.parametrize(
    "variant", [dict(num_frames=1), dict(num_frames=2), dict(num_frames=4), "no_guidance", "no_enhancement"]
)
def test_every_parameter_gets_a_gradient_so_ddp_needs_no_unused_parameter_search(tiny_cfg: RaFDConfig, variant) -> None:
    from rafd import build_model
    from rafd.data.collate import Collator
    from rafd.train.config import LossConfig
    from rafd.train.losses import RaFDLoss

    if variant == "no_guidance":
        cfg = tiny_cfg.replace(propagation=dataclasses.replace(tiny_cfg.propagation, flow_guided=False))
    elif variant == "no_enhancement":
        cfg = tiny_cfg.replace(enhance=dataclasses.replace(tiny_cfg.enhance, enabled=False))
    else:
        cfg = tiny_cfg.replace(**variant)
    model = build_model(cfg)
    frames = torch.rand(2, cfg.num_frames, 1, cfg.input_size, cfg.input_size)
    poses = torch.zeros(2, cfg.num_frames, 3)
    import numpy as np

    window = {
        "frames": (frames[0, :, 0].numpy() * 255).astype(np.uint8),
        "poses": np.zeros((cfg.num_frames, 3)),
        "boxes": [np.array([[1.0, 2.0, 1.8, 4.5, 0.2]])] * cfg.num_frames,
        "ids": [np.array([1])] * cfg.num_frames,
        "sequence": "s",
        "frame": 1,
    }
    targets = Collator(cfg)([window, window]).targets
    for flow_weight in (1.0, 0.0):  # the "without flow supervision" ablation too
        model.zero_grad()
        out = model(frames, poses, gt_indices=targets["centre_index"], gt_mask=targets["box_mask"])
        RaFDLoss(LossConfig(flow_weight=flow_weight))(out, targets)["total"].backward()
        missing = [name for name, p in model.named_parameters() if p.grad is None]
        assert not missing, f"{variant}, flow weight {flow_weight}: no gradient for {missing}"


@pytest.mark.slow
def test_rafd_train_runs_under_torchrun_with_bf16(tiny_root: Path, tmp_path: Path) -> None:
    torchrun = Path(sys.executable).with_name("torchrun")
    out = tmp_path / "ddp.pt"
    command = [
        str(torchrun),
        "--standalone",
        "--nproc_per_node",
        "2",
        "-m",
        "rafd.cli.train",
        str(tiny_root),
        "--split",
        "train",
        "--config",
        "tiny",
        "--out",
        str(out),
        "--quiet",
        "--val-split",
        "train",
        "model.num_frames=2",
        "model.input_size=64",
        "train.epochs=1",
        "train.batch_size=2",
        "train.max_steps_per_epoch=2",
        "train.precision=bf16",
        "train.device=cpu",
        "train.threads=1",
        "data.max_val_windows=3",
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert out.is_file()
    assert "[rank 0]" in done.stderr and "2 process(es)" in done.stderr and "val_mAP@0.5" in done.stderr
