"""Two CPU processes (gloo) with torchrun's environment train in lock-step: identical weights on both ranks."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import torch
import torch.multiprocessing as mp

from rafd.config import RaFDConfig
from rafd.train.datasets import open_windows
from rafd.train.distributed import cleanup_distributed, init_distributed
from rafd.train.trainer import Trainer, TrainConfig


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _worker(rank: int, world_size: int, port: int, root: str, cfg_json: str, out: str) -> None:
    # The variables torchrun sets for each process.
    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world_size), LOCAL_RANK=str(rank)
    )
    torch.set_num_threads(1)
    cfg = RaFDConfig.from_json(cfg_json)
    ctx = init_distributed("cpu")
    try:
        dataset = open_windows(root, "train", cfg)
        train_cfg = TrainConfig(epochs=1, batch_size=1, seed=5, device="cpu", progress=False, max_steps_per_epoch=2, val_every=0)
        trainer = Trainer(cfg, train_cfg, dataset, Path(out) / "model.pt", ctx)
        trainer.fit()
        torch.save({k: v.detach().cpu() for k, v in trainer.model.state_dict().items()}, Path(out) / f"rank{rank}.pt")
    finally:
        cleanup_distributed()


def test_two_gloo_processes_end_with_identical_weights(tiny_root: Path, tiny_cfg: RaFDConfig, tmp_path: Path) -> None:
    mp.spawn(_worker, args=(2, _free_port(), str(tiny_root), tiny_cfg.to_json(), str(tmp_path)), nprocs=2, join=True)
    rank0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    rank1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert rank0.keys() == rank1.keys()
    for key in rank0:
        assert torch.equal(rank0[key], rank1[key]), f"{key} differs between ranks"
    initial = _initial_weights(tiny_cfg)
    assert any(not torch.equal(rank0[k], initial[k]) for k in rank0 if rank0[k].is_floating_point()), "weights must have moved"
    assert (tmp_path / "model.pt").is_file()  # rank 0 wrote the checkpoint


def _initial_weights(cfg: RaFDConfig) -> dict[str, torch.Tensor]:
    from rafd import build_model
    from rafd.train.trainer import seed_everything

    seed_everything(5)
    return build_model(cfg).state_dict()


def test_rafd_train_runs_under_torchrun(tiny_root: Path, tmp_path: Path) -> None:
    torchrun = Path(sys.executable).with_name("torchrun")
    out = tmp_path / "ddp.pt"
    command = [
        str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "rafd.cli.train",
        "--data", str(tiny_root), "--split", "train", "--config", "tiny", "--frames", "2", "--input-size", "64",
        "--out", str(out), "--epochs", "1", "--batch-size", "1", "--max-steps-per-epoch", "2",
        "--device", "cpu", "--threads", "1", "--no-progress",
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert out.is_file()
    assert "[rank 0]" in done.stderr and "2 process(es)" in done.stderr
