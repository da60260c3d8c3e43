"""Which module of a model bf16 arithmetic hurts: the model in PyTorch with one top-level module at a time cast to
bfloat16 (weights, inputs and arithmetic; its outputs back to float32), compared with float32 on held-out simulated
windows, as the accuracy gate compares OpenVINO bf16 with onnxruntime fp32 (export/gate_run.py).

    python -m tools.bf16_modules CHECKPOINT [--sequences 2] [--sequence-frames 12] [--seed 7100]

Prints per variant: detections at the operating threshold (float32's and the variant's), the share that changed
(no partner within one feature cell), the p99 centre shift and score difference of the matched ones, and the max
heatmap difference. PyTorch rounds every result to bfloat16 on any CPU (without bf16 units it converts each operand,
only slower), so this runs where OpenVINO bf16 cannot; a runtime's own kernels may keep some operations in float32
that PyTorch rounds here, and the reverse.
"""

from __future__ import annotations

import argparse
import copy
import tempfile
from typing import Any

import numpy as np
import torch
from torch import nn

from export.gate_report import SourceFigures, compare_frame
from rafd import progress
from rafd.cli import flags
from rafd.model.checkpoint import load_checkpoint
from rafd.protocol import operating_threshold
from rafd.runtime.streaming import StepResult

MODULES = (
    "encoder.normalise",
    "encoder.backbone",
    "encoder.neck",
    "encoder.enhancement",
    "flow",
    "propagation",
    "head",
)


KEYS = ("boxes", "scores", "heatmap")


def _result(out: dict[str, np.ndarray], num_frames: int) -> StepResult:
    """One window's outputs as a runner's step result, as compare_frame reads it (no flow compared)."""
    return StepResult(out["heatmap"], out["boxes"], out["scores"], None, num_frames)


def _has(model: nn.Module, name: str) -> bool:
    try:
        model.get_submodule(name)
    except AttributeError:
        return False
    return True


def _cast(value: Any, dtype: torch.dtype) -> Any:
    """float32 tensors (and float32 tensors inside tuples, lists and dicts) to `dtype`; others unchanged."""
    source = torch.float32 if dtype == torch.bfloat16 else torch.bfloat16
    if isinstance(value, torch.Tensor):
        return value.to(dtype) if value.dtype == source else value
    if isinstance(value, (tuple, list)):
        return type(value)(_cast(v, dtype) for v in value)
    if isinstance(value, dict):
        return {k: _cast(v, dtype) for k, v in value.items()}
    return value


def in_bf16(model: nn.Module, names: list[str]) -> nn.Module:
    """A copy of `model` with the modules `names` computing in bfloat16, float32 between them."""
    variant = copy.deepcopy(model)
    for name in names:
        module = variant.get_submodule(name)
        module.to(torch.bfloat16)
        module.register_forward_pre_hook(
            lambda _m, args, kwargs: (_cast(args, torch.bfloat16), _cast(kwargs, torch.bfloat16)), with_kwargs=True
        )
        module.register_forward_hook(lambda _m, _args, output: _cast(output, torch.float32))
    return variant


def held_out_windows(cfg: Any, sequences: int, frames: int, seed: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[1, T, 1, S, S] frames and [1, T, 3] poses of every full window of freshly simulated held-out drives."""
    from rafd.data.dataset import RadarWindowDataset
    from rafd.preprocess import to_model_input
    from rafd.sim.api import simulate_dataset

    windows = []
    with tempfile.TemporaryDirectory(prefix="rafd-bf16-") as tmp:
        simulate_dataset(tmp, sequences, frames, seed, split="test", size=max(256, cfg.input_size))
        dataset = RadarWindowDataset(tmp, split="test", cfg=cfg)
        for index in range(len(dataset)):
            window = dataset.window(index)
            stacked = np.stack([to_model_input(f) for f in window["frames"]])  # [T, S, S]
            windows.append(
                (torch.from_numpy(stacked)[None, :, None], torch.from_numpy(np.asarray(window["poses"]))[None])
            )
    return windows


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.bf16_modules", description=__doc__.splitlines()[0])
    flags.add_checkpoint(parser)
    parser.add_argument(
        "--sequences", type=int, default=2, help="held-out simulated sequences, 1-50 (default %(default)s)"
    )
    parser.add_argument(
        "--sequence-frames", type=int, default=12, help="frames per simulated sequence, 5-200 (default %(default)s)"
    )
    parser.add_argument("--seed", type=int, default=7100, help="simulation seed (the gate's default: held out)")
    parser.add_argument("--keep-fp32", help="also: every module in bf16 but these (comma-separated) in float32")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    if not 1 <= args.sequences <= 50 or not 5 <= args.sequence_frames <= 200:
        parser.error("--sequences 1-50, --sequence-frames 5-200")
    torch.manual_seed(0)
    model, cfg, meta = load_checkpoint(args.checkpoint)
    threshold = operating_threshold(meta)
    windows = held_out_windows(cfg, args.sequences, args.sequence_frames, args.seed)
    present = [name for name in MODULES if _has(model, name)]
    variants = {"float32": model, "every module in bf16": in_bf16(model, present)}
    variants.update({f"{name} in bf16": in_bf16(model, [name]) for name in present})
    kept = [name for name in (args.keep_fp32 or "").split(",") if name]
    if set(kept) - set(present):
        parser.error(f"--keep-fp32 takes modules from {', '.join(present)}")
    if kept:
        variants[f"all but {'+'.join(kept)}"] = in_bf16(model, [n for n in present if n not in kept])
    outputs: dict[str, list[dict[str, np.ndarray]]] = {name: [] for name in variants}
    failed: dict[str, str] = {}
    with torch.inference_mode():
        for frames, poses in progress.track(windows, desc="held-out windows", unit="window"):
            for name, variant in variants.items():
                if name in failed:
                    continue
                try:
                    out = variant(frames, poses)
                except RuntimeError as error:  # an operation without a bf16 kernel on this CPU
                    failed[name] = str(error).splitlines()[0][:100]
                    continue
                outputs[name].append({k: out[k].float().numpy()[0] for k in KEYS})
    print(f"{len(windows)} held-out windows (seed {args.seed}), threshold {threshold:.4f}, cell {cfg.cell_size} m")
    print(
        f"{'variant':<36} {'dets fp32/var':>14} {'changed':>8} {'centre p99 m':>13} {'score p99':>10} {'heat max':>9}"
    )
    print("(heat max: the largest heatmap difference; non-finite: the variant's outputs hold NaN or infinity)")
    for name in variants:
        if name == "float32":
            continue
        if name in failed:
            print(f"{name:<36} cannot run: {failed[name]}")
            continue
        if not all(np.isfinite(v).all() for out in outputs[name] for v in out.values()):
            print(f"{name:<36} non-finite outputs")
            continue
        figures = SourceFigures()
        heat = 0.0
        for ref, cand in zip(outputs["float32"], outputs[name]):  # the gate's matching and figures
            compare_frame(figures, _result(ref, cfg.num_frames), _result(cand, cfg.num_frames), cfg, threshold)
            heat = max(heat, float(np.abs(ref["heatmap"] - cand["heatmap"]).max()))
        counts = f"{figures.reference_detections}/{figures.candidate_detections}"
        print(
            f"{name:<36} {counts:>14} {figures.changed_fraction:>8.1%} {figures.centre_p99:>13.3f} "
            f"{figures.score_p99:>10.4f} {heat:>9.4f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
