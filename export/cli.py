"""rafd export: a checkpoint to ONNX, checked against PyTorch, with the accuracy gate of reduced precision.

`rafd-export checkpoint.pt model.onnx` (the output positional) is kept as it always was; `--out model.onnx` is the
same, in the shared vocabulary (docs/cli.md).
"""

from __future__ import annotations

import argparse
import sys

from export import MIN_OPSET
from export.gate_cli import add_gate_flags, gate_options
from rafd.cli import flags


def _opset(text: str) -> int:
    value = int(text)
    if value < MIN_OPSET:
        raise argparse.ArgumentTypeError(f"opset must be >= {MIN_OPSET} (GridSample), got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("export"),
        description="Export a RaFD checkpoint to ONNX (static shapes, metadata for the service) and verify it "
        "with onnxruntime against PyTorch (random inputs, plus real frames when RAFD_RADIATE_SAMPLE "
        "names a RADIATE sequence).",
    )
    flags.add_checkpoint(parser)
    parser.add_argument(
        "output",
        nargs="?",
        metavar="OUTPUT.onnx",
        help="ONNX file to write (replaced atomically, only after verification); or --out",
    )
    flags.add_out(parser, "MODEL.onnx", "ONNX file to write (the same as the positional OUTPUT.onnx)", type=str)
    parser.add_argument(
        "--opset", type=_opset, default=MIN_OPSET, help=f"ONNX opset, >= {MIN_OPSET} (default %(default)s)"
    )
    parser.add_argument(
        "--batch",
        choices=("static", "dynamic"),
        default="dynamic",
        help="dynamic: a free first axis, so the tiles of a whole scan step as one batch (verified batched too); "
        "static: a batch of one (a whole scan then steps tile by tile) (default %(default)s)",
    )
    parser.add_argument("--no-verify", action="store_true", help="skip the onnxruntime vs PyTorch parity check")
    gate = parser.add_argument_group(
        "accuracy gate",
        "reduced precision (OpenVINO bf16, where the CPU has it) against onnxruntime fp32 on held-out "
        "simulated sequences and, with RAFD_RADIATE_SAMPLE, the real sample's frames; the verdict is recorded in the "
        "ONNX metadata (the service picks bf16 automatically only after a pass)",
    )
    gate.add_argument("--gate", action="store_true", help="run the accuracy gate")
    add_gate_flags(gate)
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if (args.output is None) == (args.out is None):
        parser.error("give the ONNX file to write once: OUTPUT.onnx or --out MODEL.onnx")
    output = args.output or args.out
    flags.apply_quiet(args)
    flags.exit_on_sigterm()  # a killed export removes its temporary files beside the output
    # Heavy imports (torch, onnx) after argument parsing: --help stays fast.
    from export.onnx_export import ExportError, export_onnx
    from export.verify import VerificationError
    from rafd.model.checkpoint import CheckpointError

    def log(message: str) -> None:
        print(message, flush=True)

    gate = None
    if args.gate:
        gate = gate_options(args)
    try:
        result = export_onnx(
            args.checkpoint,
            output,
            opset=args.opset,
            verify=not args.no_verify,
            log=log,
            gate=gate,
            batch=args.batch,
        )
    except CheckpointError as error:
        print(f"{parser.prog}: error: bad checkpoint: {error}", file=sys.stderr)
        return 1
    except (ExportError, VerificationError) as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 1
    verified = "verified" if result.report is not None else "not verified (--no-verify)"
    gated = "".join(
        f", {precision} gate {'PASS' if report.ok else 'FAIL'}" for precision, report in result.gates.items()
    )
    batch = ", dynamic batch" if result.metadata.get("batch") == "dynamic" else ""
    print(
        f"wrote {result.path} ({result.size_bytes / 1e6:.2f} MB, step graph{batch}, opset {result.opset}, "
        f"{result.exporter} exporter, {verified}{gated})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
