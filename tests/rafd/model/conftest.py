"""Small configs for the model tests: every module runs, each test takes a second or two on a CPU."""

from __future__ import annotations

import pytest
import torch

from rafd.config import RaFDConfig


def small_config(num_frames: int = 4, **overrides) -> RaFDConfig:
    """The tiny network at 64 px (16 x 16 cells, 16 queries)."""
    cfg = RaFDConfig.tiny(input_size=64, num_frames=num_frames, **overrides)
    return cfg.replace(head=cfg.head.__class__(num_queries=16, decoder_layers=1, num_points=4))


def random_inputs(cfg: RaFDConfig, batch: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """frames [B, T, 1, S, S] in [0, 1] and world poses [B, T, 3] of a vehicle driving forward and turning."""
    generator = torch.Generator().manual_seed(seed)
    frames = torch.rand(batch, cfg.num_frames, 1, cfg.input_size, cfg.input_size, generator=generator)
    steps = torch.arange(cfg.num_frames, dtype=torch.float32)
    start = torch.rand(batch, 1, 3, generator=generator) * torch.tensor([50.0, 50.0, 3.0])
    motion = torch.stack([0.2 * steps, 1.5 * steps, 0.03 * steps], dim=-1)  # [T, 3]
    return frames, start + motion[None]


@pytest.fixture(autouse=True)
def _deterministic_single_thread():
    """Seeded, one intra-op thread: these ops are tiny, and on a shared 2-core machine two OpenMP threads
    fighting other jobs made the suite 5x slower (35 s vs 6.5 s). The previous setting is restored."""
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def make_config():
    """small_config as a fixture (test folders are not packages, so helpers travel as fixtures)."""
    return small_config


@pytest.fixture
def make_inputs():
    return random_inputs
