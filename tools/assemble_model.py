"""A multi-frame model assembled from a single-frame model's encoder + head and a multi-frame model's flow branch +
propagation: the shipped recipe's two stages with the second one taken from an existing model, e.g. a single-frame
model fine-tuned on a few real scans put back into the shipped 4-frame model (docs/finetuning.md).

    python -m tools.assemble_model SINGLE.pt MULTI.pt --out OUT.pt

The two must be the same network but for the frame count. The result keeps SINGLE's meta (its training) without an
operating threshold: calibrate it (`rafd eval OUT.pt ... --calibrate FP_PER_FRAME`) before serving it.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def assemble(single: Path, multi: Path, out: Path) -> dict[str, int]:
    """Write OUT -> how many tensors came from each model; ValueError when the two networks differ."""
    from rafd.model import build_model
    from rafd.model.checkpoint import read_checkpoint, save_checkpoint
    from rafd.protocol import OPERATING_THRESHOLD_KEY

    single_state, single_cfg, single_meta = read_checkpoint(single)
    multi_state, cfg, _ = read_checkpoint(multi)
    if single_cfg.num_frames != 1 or cfg.num_frames < 2:
        raise ValueError(f"{single} must be a 1-frame model and {multi} a multi-frame one")
    if single_cfg != cfg.replace(num_frames=1):
        raise ValueError(f"{single} and {multi} are not the same network but for the frame count")
    state = {name: single_state.get(name, tensor) for name, tensor in multi_state.items()}
    model = build_model(cfg)
    model.load_state_dict(state, strict=True)
    meta = {k: v for k, v in single_meta.items() if k not in (OPERATING_THRESHOLD_KEY, "operating_point")}
    meta["assembled"] = f"encoder + head of {single}, flow branch + propagation of {multi}"
    save_checkpoint(out, model, cfg, meta=meta)
    from_single = sum(name in single_state for name in multi_state)
    return {"single": from_single, "multi": len(multi_state) - from_single}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.assemble_model", description=__doc__.split("\n\n")[0])
    parser.add_argument("single", type=Path, metavar="SINGLE.pt", help="the 1-frame model: its encoder and head")
    parser.add_argument("multi", type=Path, metavar="MULTI.pt", help="the multi-frame model: its flow and propagation")
    parser.add_argument("--out", type=Path, required=True, metavar="OUT.pt", help="the assembled checkpoint to write")
    args = parser.parse_args(argv)
    try:
        counts = assemble(args.single, args.multi, args.out)
    except ValueError as error:
        print(f"assemble_model: error: {error}", file=sys.stderr)
        return 2
    print(f"{args.out}: {counts['single']} tensors from {args.single}, {counts['multi']} from {args.multi}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
