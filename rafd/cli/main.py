"""`rafd COMMAND [ARGS]`: one command for every tool, in the manner of git.

`COMMANDS` is the one table of the commands: name, "module:function", summary. A command's module is imported only
when that command runs, so `rafd --help` stays fast and this package imports none of the layers above it (export,
service). `rafd bench NAME` runs the command `bench-NAME`. Each command outside a group has a `rafd-*` script, an
alias of it (`rafd-serve` = `rafd serve`; pyproject.toml's [project.scripts], which a test checks against this
table); the benchmarks are `rafd bench NAME` only. An experiment is not a command: it is a script in tools/ while
it is needed, and goes once its finding is recorded (docs/archive.md).

Another package adds a command by declaring an entry point of the group `rafd.commands` (found with
importlib.metadata); a name of this table stays this table's.
"""

from __future__ import annotations

import difflib
import importlib
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import metadata

from rafd import __version__
from rafd.cli import flags

GROUP = "rafd.commands"


@dataclass(frozen=True)
class Command:
    name: str  # as typed after `rafd` ("bench-speed" is typed `rafd bench speed`)
    target: str  # "module:function", the function taking argv and returning the exit status
    summary: str


# What `rafd --help` says of each command, in this order.
COMMANDS = (
    Command("serve", "service.cli:main", "serve the model over HTTP (FastAPI, onnxruntime or OpenVINO, no torch)"),
    Command("client", "rafd.cli.client:main", "stream a RADIATE-format sequence to a running service"),
    Command("export", "export.cli:main", "export a checkpoint to ONNX; parity with PyTorch; the accuracy gate"),
    Command("gate", "export.gate_cli:main", "run the accuracy gate of reduced precision on an ONNX model; record it"),
    Command("train", "rafd.cli.train:main", "train RaFD (one process, or several under torchrun)"),
    Command("eval", "rafd.cli.evaluate:main", "score a checkpoint on a split: mAP, centre matching, EPE; calibrate"),
    Command("simulate", "rafd.cli.simulate:main", "simulate RADIATE-format sequences; realism against real scans"),
    Command("odometry", "rafd.cli.odometry:main", "write ego_poses.csv by radar odometry; evaluate against true poses"),
    Command("prepare", "rafd.cli.prepare:main", "decode a data root's scans once into a memory-mapped scan cache"),
    Command("polar", "rafd.cli.polar:main", "convert polar or native scans to RADIATE's Cartesian grid; compare"),
    Command("label", "rafd.cli.label:main", "label real scans: candidates, box text -> RADIATE labels, compare, link"),
    Command("bench-speed", "bench.speed_cli:main", "speed, accuracy drift and memory of every runtime and precision"),
    Command("bench-accuracy", "bench.accuracy_cli:main", "the synthetic accuracy benchmark: data, run, compare"),
    Command("bench-training", "bench.training_cli:main", "training speed: input pipeline, fp32 against bf16"),
    Command("bench-capacity", "bench.capacity_cli:main", "streams per replica at 4 Hz within a p99 budget"),
)
SUMMARIES = {c.name: c.summary for c in COMMANDS}
GROUPS = {
    "bench": "benchmarks (package bench/): what a frame and a replica cost, how accurate a model is, training's speed"
}


def installed_commands() -> dict[str, str]:
    """name -> "module:function" of every command: the table's, and those other packages declare as entry points."""
    table = {c.name: c.target for c in COMMANDS}
    declared = {ep.name: ep.value for ep in metadata.entry_points(group=GROUP) if ep.name not in table}
    return {**table, **declared}


def load(target: str) -> Callable[[Sequence[str] | None], int]:
    module, _, function = target.partition(":")
    main: Callable[[Sequence[str] | None], int] = getattr(importlib.import_module(module), function)
    return main


def _typed(name: str) -> str:
    return name.replace("-", " ", 1) if name.split("-", 1)[0] in GROUPS else name


def usage(commands: dict[str, str]) -> str:
    names = sorted(commands, key=lambda n: (list(SUMMARIES).index(n) if n in SUMMARIES else len(SUMMARIES), n))
    width = max(len(_typed(n)) for n in names) + 2
    lines = [
        "usage: rafd [--version] [-h] COMMAND [ARGS]",
        "",
        "RaFD: radar object detection, from training to the HTTP service. `rafd COMMAND --help` shows a command's "
        "flags;",
        "every command outside `rafd bench` is also installed as `rafd-COMMAND` (`rafd serve` as `rafd-serve`).",
        "",
        "commands:",
    ]
    lines += [f"  {_typed(n):<{width}}{SUMMARIES.get(n, '(installed by another package)')}" for n in names]
    lines += ["", "Shared flags (the same meaning in every command): docs/cli.md"]
    return "\n".join(lines)


def group_usage(group: str, commands: dict[str, str]) -> str:
    members = [n for n in commands if n.startswith(group + "-")]
    lines = [f"usage: rafd {group} {{{','.join(n.split('-', 1)[1] for n in members)}}} [ARGS]", "", GROUPS[group], ""]
    width = max(len(n) for n in members) - len(group)
    lines += [f"  {n.split('-', 1)[1]:<{width}}{SUMMARIES.get(n, '')}" for n in members]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    commands = installed_commands()
    if not args or args[0] in ("-h", "--help", "help"):
        print(usage(commands), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    if args[0] == "--version":
        print(f"rafd {__version__}")
        return 0
    name, rest = args[0], args[1:]
    if name in GROUPS:
        if not rest or rest[0] in ("-h", "--help"):
            print(group_usage(name, commands), file=sys.stdout if rest else sys.stderr)
            return 0 if rest else 2
        name, rest = f"{name}-{rest[0]}", rest[1:]
    if name not in commands:
        typed = [_typed(n) for n in commands]
        close = difflib.get_close_matches(name.replace("-", " "), typed, n=1)
        hint = f"; did you mean `rafd {close[0]}`?" if close else ""
        print(f"rafd: unknown command {name.replace('-', ' ')!r}{hint} (rafd --help lists them)", file=sys.stderr)
        return 2
    flags.set_dispatched(True)
    try:
        return int(load(commands[name])(rest) or 0)
    finally:
        flags.set_dispatched(False)


if __name__ == "__main__":
    sys.exit(main())
