"""Whether OpenVINO keeps nodes marked for float32 in float32 under bf16: the runtime precision of each layer type of
an ONNX model compiled with INFERENCE_PRECISION_HINT bf16, unmarked against marked (issue 41 item 2, fp32 islands).

    python -m tools.precision_marks [MODEL.onnx] [--types Convolution,MatMul] [--scope /flow/] [--marks precise_0,...]

The marks are rt_info keys set to "" on the chosen nodes after `core.read_model` (every node of --types, or whose
name starts with --scope): `precise_0` (the name this OpenVINO's serializer uses) and `disable_fp16_compression_0`
(its older name). Printed per mark: (layer type, runtime precision) -> nodes, from `compiled.get_runtime_model()`,
and whether any count changed. Needs a CPU OpenVINO runs bf16 on (avx512_bf16 or AMX); elsewhere it says so.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rafd.cli import flags
from rafd.runtime.openvino_backend import openvino_supports_bf16, runtime_precisions

MARKS = ("precise_0", "disable_fp16_compression_0")
# The layer types printed: the arithmetic the precision decides (every type still counts for "changed").
SHOWN = ("Convolution", "FullyConnected", "MatMul", "Eltwise", "GridSample", "Interpolate", "MVN", "Softmax")


def shown(counts: dict[tuple[str, str], int]) -> str:
    return ", ".join(f"{kind} {precision}: {n}" for (kind, precision), n in sorted(counts.items()) if kind in SHOWN)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.precision_marks", description=__doc__.splitlines()[0])
    parser.add_argument("model", nargs="?", type=Path, help="ONNX model (default: the shipped one)")
    parser.add_argument(
        "--types", default="Convolution,MatMul", help="comma-separated node types to mark (default %(default)s)"
    )
    parser.add_argument("--scope", help="mark instead every node whose name starts with this (e.g. /flow/)")
    parser.add_argument("--marks", default=",".join(MARKS), help="comma-separated rt_info keys (default: both names)")
    flags.add_quiet(parser)
    return parser


def compile_marked(model_path: Path, mark: str | None, chosen: Any) -> dict[tuple[str, str], int]:
    """The runtime precisions of `model_path` compiled in bf16, the nodes `chosen(node)` picks marked with `mark`."""
    import openvino as ov

    core = ov.Core()
    model = core.read_model(str(model_path))
    if mark is not None:
        for node in model.get_ops():
            if chosen(node):
                node.get_rt_info()[mark] = ""
    return runtime_precisions(core.compile_model(model, "CPU", {"INFERENCE_PRECISION_HINT": "bf16"}))


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    if not openvino_supports_bf16():
        print(f"{parser.prog}: this CPU has no bf16 that OpenVINO runs: nothing to compare", file=sys.stderr)
        return 2
    if args.model is None:
        from rafd.assets import default_onnx

        args.model = default_onnx()
    if not args.model.is_file():
        parser.error(f"{args.model} is not a file")
    types = {name for name in args.types.split(",") if name}
    if args.scope:
        chosen = lambda node: node.get_friendly_name().startswith(args.scope)  # noqa: E731
    else:
        chosen = lambda node: node.get_type_name() in types  # noqa: E731
    unmarked = compile_marked(args.model, None, chosen)
    print(f"{args.model.name}, compiled with INFERENCE_PRECISION_HINT bf16: nodes by (layer type, runtime precision)")
    print(f"unmarked: {shown(unmarked)}")
    for mark in (m for m in args.marks.split(",") if m):
        marked = compile_marked(args.model, mark, chosen)
        verdict = "changed" if marked != unmarked else "the same as unmarked: the mark is not honoured"
        print(f"{mark}: {shown(marked)} ({verdict})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
