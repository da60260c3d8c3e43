"""The exported graph: the model's streaming step (RaFD.step) with its cache as named inputs and outputs.

    inputs   frame [B, 1, S, S], pose [B, 3], cache.NAME ... (the names and shapes of RaFD.empty_cache)
    outputs  heatmap [B, 1, Hf, Wf], scores [B, K], boxes [B, K, 5], flow [B, 2, Hf, Wf] (T > 1), frames_used [B],
             new_cache.NAME ... (each the shape of its cache.NAME)

The contract the runtime reads (rafd.runtime.contract): it feeds new_cache.NAME back as cache.NAME and never looks
inside.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from rafd.config import RaFDConfig
from rafd.model import RaFD
from rafd.runtime.contract import CACHE_PREFIX, NEW_CACHE_PREFIX, STEP_OUTPUTS


class StepGraph(nn.Module):
    """RaFD.step with its cache flattened into positional tensors, in the order of `cache_names`."""

    def __init__(self, model: RaFD, cache_names: tuple[str, ...]) -> None:
        super().__init__()
        self.model = model
        self.cache_names = cache_names
        self.outputs = STEP_OUTPUTS if model.num_frames > 1 else tuple(n for n in STEP_OUTPUTS if n != "flow")

    def forward(self, frame: Tensor, pose: Tensor, *cache: Tensor) -> tuple[Tensor, ...]:
        outputs, new_cache = self.model.step(frame, pose, dict(zip(self.cache_names, cache)))
        return tuple(outputs[name] for name in self.outputs) + tuple(new_cache[name] for name in self.cache_names)

    @property
    def input_names(self) -> tuple[str, ...]:
        return ("frame", "pose") + tuple(CACHE_PREFIX + name for name in self.cache_names)

    @property
    def output_names(self) -> tuple[str, ...]:
        return self.outputs + tuple(NEW_CACHE_PREFIX + name for name in self.cache_names)


def build_graph(model: RaFD, cfg: RaFDConfig) -> tuple[StepGraph, tuple[Tensor, ...]]:
    """The step graph of an eval-mode model and example inputs of its static shapes (random frame, a small ego
    motion, a random cache of a started stream), in input order."""
    model = model.eval()
    cache = model.empty_cache(1, cfg.input_size)
    graph = StepGraph(model, tuple(cache))
    generator = torch.Generator().manual_seed(0)
    size = cfg.input_size
    example = [torch.rand(1, 1, size, size, generator=generator), torch.tensor([[0.3, 1.5, 0.02]])]
    for name, zeros in cache.items():
        example.append(
            torch.full_like(zeros, 2.0) if name == "frames" else torch.randn(zeros.shape, generator=generator)
        )
    return graph.eval(), tuple(example)
