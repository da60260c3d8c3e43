"""rafd gate: run the accuracy gate of every reduced precision this CPU has on an exported ONNX model and record the
verdicts in the model's metadata, without re-exporting (the checkpoint is not needed).

`rafd export --gate` does the same at export time; this command is for a model exported on a CPU that had no bf16
(the verdicts are what lets `rafd serve` pick a reduced precision automatically).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from export.quantize import CALIBRATION_FRAMES, CALIBRATION_SEQUENCES
from rafd.cli import flags

if TYPE_CHECKING:
    from export.gate_options import GateOptions


def add_gate_flags(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The gate's flags, shared by `rafd gate` and `rafd export --gate`."""
    parser.add_argument(
        "--gate-sequences", type=flags.positive_int, default=12, help="simulated sequences (default %(default)s)"
    )
    parser.add_argument(
        "--gate-sequence-frames",
        dest="gate_frames",
        type=flags.positive_int,
        default=60,
        metavar="N",
        help="frames per simulated sequence (default %(default)s)",
    )
    parser.add_argument(
        "--no-islands",
        dest="islands",
        action="store_false",
        help="where plain bf16 or int8 fails its gate, do not search for float32 islands that pass (the search "
        "runs short gates of each matrix unit added to the islands so far, and the full gate where one comes close; "
        "bf16 keeps the graph's matrix-free units in float32 from the start: export/islands_gate.py)",
    )
    parser.add_argument(
        "--calibration-sequences",
        type=flags.positive_int,
        default=CALIBRATION_SEQUENCES,
        metavar="N",
        help="simulated sequences whose activations calibrate int8 (default %(default)s)",
    )
    parser.add_argument(
        "--calibration-frames",
        type=flags.positive_int,
        default=CALIBRATION_FRAMES,
        metavar="N",
        help="frames per calibration sequence (default %(default)s)",
    )
    parser.add_argument(
        "--gate-seed",
        type=int,
        default=None,
        help="simulation seed; must be one the model was never trained or tested on "
        "(default: export.gate_options.DEFAULT_SEED)",
    )


def gate_options(args: argparse.Namespace, threads: int | None = None) -> GateOptions:
    """The options add_gate_flags parsed."""
    from export.gate_options import DEFAULT_SEED, GateOptions

    return GateOptions(
        sequences=args.gate_sequences,
        frames=args.gate_frames,
        seed=DEFAULT_SEED if args.gate_seed is None else args.gate_seed,
        threads=threads,
        islands=args.islands,
        calibration_sequences=args.calibration_sequences,
        calibration_frames=args.calibration_frames,
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("gate"),
        description="Run the accuracy gate of every reduced precision this CPU runs (OpenVINO bf16 where the CPU has "
        "avx512_bf16 or AMX; OpenVINO int8 where it has VNNI or AMX, on MODEL.int8.onnx, which this command "
        "quantizes first, calibrated on other simulated sequences) against onnxruntime fp32 on held-out "
        "simulated sequences and, with RAFD_RADIATE_SAMPLE, the real sample's frames; record each verdict and "
        "its figures in the ONNX model's metadata (in place unless --out). The service picks a reduced "
        "precision automatically only after a recorded pass.",
    )
    parser.add_argument("model", metavar="MODEL.onnx", type=Path, help="the exported ONNX model (step form)")
    flags.add_out(parser, "MODEL.onnx", "write the gated model here instead of replacing MODEL.onnx", type=Path)
    add_gate_flags(parser)
    flags.add_threads(parser, None, "onnxruntime's and OpenVINO's threads per run (default: every usable core)")
    flags.add_quiet(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    flags.exit_on_sigterm()  # a killed gate removes its temporary models and islands folders
    from rafd.model_files import checkpoint_given_for_onnx, int8_model_path, islands_dir

    if not args.model.is_file():
        print(f"{parser.prog}: error: {args.model} is not a file", file=sys.stderr)
        return 1
    wrong_kind = checkpoint_given_for_onnx(args.model)
    if wrong_kind:
        print(f"{parser.prog}: error: {wrong_kind}", file=sys.stderr)
        return 1
    # Heavy imports (torch for the simulated windows, onnx) after argument parsing: --help stays fast.
    from export.gate import gate_and_record

    options = gate_options(args, args.threads)
    target = args.out or args.model
    start = time.perf_counter()
    try:
        reports = gate_and_record(args.model, options, args.out, lambda message: print(message, flush=True))
    except ValueError as error:  # not a RaFD step graph, or not loadable
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 1
    seconds = time.perf_counter() - start
    if not reports:
        print(f"nothing recorded: {args.model} is unchanged")
        return 0
    beside = {"bf16": f"{islands_dir(target).name}/", "int8": int8_model_path(target).name}  # the islands' files
    verdicts = ", ".join(
        f"{precision} gate {'PASS' if r.ok else 'FAIL'}"
        + (f" with float32 islands {', '.join(r.islands)} ({beside[precision]})" if r.islands else "")
        for precision, r in reports.items()
    )
    print(f"recorded in {target}: {verdicts} ({seconds:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
