"""The flags every command shares, defined once: each `add_*` function adds one flag with its one meaning and help.

The vocabulary (docs/cli.md, "Shared flags", lists it with the commands that take each flag):

- inputs are positional (`rafd eval CHECKPOINT ROOT`, `rafd prepare ROOT`);
- the main output is `--out`, its metavar naming what it is (`--out CKPT`, `--out DIR`, `--out CSV`); further
  outputs are named for what they hold (`--json FILE`, `--plots DIR`, `--mcap FILE`, `--mcap-dir DIR`);
- `--split` is repeatable and comma-separable everywhere;
- `--workers N` parallel worker processes, `--threads N` CPU threads of the model, `--device`, `--config`;
- `--sequence-frames N` frames per sequence (a window's frames are the model's: `rafd train ...
  model.num_frames=N`);
- `--resume` has one meaning: continue the unfinished run in `--out` from its last finished epoch;
- `--quiet` silences the progress bars (rafd.progress).
"""

from __future__ import annotations

import argparse
import signal
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from rafd import progress

# `X | None` -> X, for the flags made from typed fields (service.serve_flags: one per Settings field)
from rafd.config_tree import without_none as without_none

# Set by `rafd` (rafd.cli.main) while it runs a command: usage lines then read `rafd serve`, not `rafd-serve`.
_dispatched = False


def set_dispatched(value: bool) -> None:
    global _dispatched
    _dispatched = value


def prog(command: str) -> str:
    """The program name in usage lines: `rafd COMMAND` under the `rafd` dispatcher or for a command of a group (`rafd
    bench speed`, which has no alias), else the `rafd-COMMAND` alias."""
    return f"rafd {command}" if _dispatched or " " in command else f"rafd-{command}"


def split_names(values: Sequence[str] | None) -> tuple[str, ...]:
    """--split given repeated and/or comma-separated -> the split names in order."""
    return tuple(name.strip() for value in values or () for name in value.split(",") if name.strip())


# ----------------------------------------------------------------------------- the shared flags
def add_split(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    what: str = "the splits to use",
    required: bool = False,
    flag: str = "--split",
    dest: str | None = None,
) -> None:
    """--split NAME: meta.json 'set' names, repeated and/or comma-separated."""
    parser.add_argument(
        flag,
        dest=dest,
        action="append",
        required=required,
        metavar="NAME",
        help=f"{what}: meta.json 'set' names, repeat or comma-separate (e.g. train_good_weather,test)",
    )


def add_out(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    metavar: str,
    what: str,
    required: bool = False,
    type: Callable[[str], Any] = Path,
) -> None:
    """--out THING: the command's main output, its metavar naming what it is."""
    parser.add_argument("--out", type=type, metavar=metavar, required=required, default=None, help=what)


def add_workers(parser: argparse.ArgumentParser | argparse._ArgumentGroup, default: int | None, what: str) -> None:
    """--workers N: parallel worker processes."""
    parser.add_argument("--workers", type=int, default=default, metavar="N", help=f"parallel worker processes: {what}")


def add_threads(parser: argparse.ArgumentParser | argparse._ArgumentGroup, default: int | None, what: str) -> None:
    """--threads N: CPU threads of the model (torch in training and evaluation, the inference runtime elsewhere)."""
    parser.add_argument(
        "--threads", type=positive_int, default=default, metavar="N", help=f"CPU threads of the model: {what}"
    )


def add_device(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--device: where torch runs."""
    parser.add_argument("--device", default="auto", help="torch device: cpu | cuda | cuda:N | auto (default: auto)")


def add_config(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, choices: Iterable[str], default: str, what: str
) -> None:
    """--config NAME: the recipe (network configuration and training settings, rafd.train.recipes)."""
    parser.add_argument(
        "--config",
        choices=sorted(choices),
        default=default,
        help=f"recipe (rafd.train.recipes), default {default}: {what}",
    )


def add_sequence_frames(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, default: int | None, what: str = ""
) -> None:
    """--sequence-frames N: frames per simulated sequence."""
    parser.add_argument(
        "--sequence-frames",
        dest="frames",
        type=int,
        default=default,
        metavar="N",
        help="frames per sequence" + (f" ({what})" if what else "") + (f", default {default}" if default else ""),
    )


def add_resume(parser: argparse.ArgumentParser | argparse._ArgumentGroup, what: str) -> None:
    """--resume: continue the unfinished run in --out from its last finished epoch."""
    parser.add_argument(
        "--resume",
        action="store_true",
        help=f"continue the unfinished run in --out from its last finished epoch: {what}",
    )


def add_warm_up_windows(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--warm-up-windows: each sequence's first T-1 frames as windows too, padded as the service pads a stream's
    first frames (without it, only full windows: the paper's protocol)."""
    parser.add_argument(
        "--warm-up-windows",
        action="store_true",
        help="also each sequence's first frames, in windows padded as the service pads a new stream's "
        "(a short real sequence keeps all its labelled frames)",
    )


def add_quiet(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """--quiet: no progress bars (rafd.progress); results and errors are still printed."""
    parser.add_argument("--quiet", action="store_true", help="no progress bars; results and errors are still printed")


def add_checkpoint(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, nargs: str | None = None, what: str = ""
) -> None:
    """CHECKPOINT: a checkpoint written by rafd train (positional: an input)."""
    parser.add_argument(
        "checkpoint",
        type=Path,
        nargs=nargs,
        metavar="CHECKPOINT",
        help="checkpoint written by rafd train (.pt)" + (f"; {what}" if what else ""),
    )


def apply_quiet(args: argparse.Namespace) -> None:
    """Apply --quiet to every progress bar of this process."""
    progress.set_quiet(bool(getattr(args, "quiet", False)))


def parse(
    build_parser: Callable[[], argparse.ArgumentParser], argv: Sequence[str] | None
) -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    """A command's parser built and `argv` parsed with it, --quiet applied -> (parser, args): the parser for
    parser.error() on what argparse cannot check alone."""
    parser = build_parser()
    args = parser.parse_args(argv)
    apply_quiet(args)
    return parser, args


def exit_on_sigterm() -> None:
    """SIGTERM (a `kill`, a container's stop) ends the command as SystemExit(143), so its `finally` blocks remove
    the temporary files it writes beside models (Python's default for SIGTERM ends the process where it stands and
    leaves them). For the commands that write such files (rafd export, rafd gate); the service keeps uvicorn's
    graceful shutdown."""

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


# ----------------------------------------------------------------------------- value types
def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def int_in(low: int, high: int) -> Callable[[str], int]:
    """An argparse type: an integer from low to high inclusive (a benchmark's bounded counts)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(f"an integer, got {text!r}") from error
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be {low}-{high}, got {value}")
        return value

    return parse


def int_list(text: str) -> list[int]:
    """'1,2,8' -> [1, 2, 8]."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"a comma-separated list of integers, got {text!r}") from error
    if not values:
        raise argparse.ArgumentTypeError("at least one value")
    return values
