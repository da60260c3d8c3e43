"""The PyTorch model as a rafd.runtime Backend: its streaming step (RaFD.step) run on numpy feeds, so evaluation
streams a checkpoint through the same runner and whole-view code as the service streams its ONNX graph."""

from __future__ import annotations

import numpy as np
import torch

from rafd.config import RaFDConfig
from rafd.model import RaFD
from rafd.model.precision import autocast
from rafd.runtime.backend import DYNAMIC
from rafd.runtime.contract import CACHE_PREFIX, NEW_CACHE_PREFIX, STEP_OUTPUTS


class TorchBackend:
    """RaFD.step in eval mode, fp32 or bf16 autocast, on `device`; `run` as the exported graph's."""

    runtime = "pytorch"
    concurrent_runs = 1

    def __init__(self, model: RaFD, cfg: RaFDConfig, device: torch.device | str = "cpu", precision: str = "fp32"):
        self.model = model.eval()
        self.device = torch.device(device)
        self.precision = precision
        self.threads = torch.get_num_threads()
        self.metadata = {"config": cfg.to_json(), "version": "pytorch"}
        cache = model.empty_cache(1, cfg.input_size)
        self.cache_names = tuple(cache)
        size = cfg.input_size
        self.input_shapes: dict[str, tuple[int, ...]] = {"frame": (DYNAMIC, 1, size, size), "pose": (DYNAMIC, 3)}
        self.input_shapes |= {CACHE_PREFIX + name: (DYNAMIC, *value.shape[1:]) for name, value in cache.items()}
        outputs = STEP_OUTPUTS if cfg.num_frames > 1 else tuple(n for n in STEP_OUTPUTS if n != "flow")
        self.output_names = outputs + tuple(NEW_CACHE_PREFIX + name for name in self.cache_names)

    @torch.no_grad()
    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        tensor = {name: torch.from_numpy(np.ascontiguousarray(value)).to(self.device) for name, value in feeds.items()}
        cache = {name: tensor[CACHE_PREFIX + name] for name in self.cache_names}
        with autocast(self.device, self.precision):
            outputs, new_cache = self.model.step(tensor["frame"], tensor["pose"], cache)
        named = {**outputs, **{NEW_CACHE_PREFIX + name: value for name, value in new_cache.items()}}
        return {name: named[name].float().cpu().numpy() for name in self.output_names}
