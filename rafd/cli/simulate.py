"""rafd simulate: write synthetic Navtech sequences in RADIATE's format, or a sim-vs-real preview."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

from rafd.cli import flags
from rafd.geometry import RADIATE_SCAN_SIZE
from rafd.sim.api import simulate_dataset
from rafd.sim.preview import render_preview
from rafd.sim.sensor import WEATHER_PROBABILITIES, WEATHERS, Difficulty


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("simulate"),
        description="Simulate RADIATE-format radar sequences (Navtech_Cartesian/, annotations, meta.json, "
        "ego_poses.csv) into --out DIR; with --realism, compare simulated with real scans; with --preview, draw a "
        "simulated scan beside a real one.",
    )
    flags.add_out(parser, "DIR|PNG", "folder receiving sim_<seed>_<k>/ sequence folders (with --preview: the PNG)")
    parser.add_argument("--sequences", type=int, default=1, help="number of sequences (default 1)")
    flags.add_sequence_frames(parser, 50)
    parser.add_argument(
        "--seed", type=int, default=0, help="dataset seed; sequence k uses a seed derived from (seed, k)"
    )
    flags.add_split(
        parser,
        "meta.json 'set' of the written sequences (default train_good_weather); several: the sequences are dealt "
        "to them in turn",
    )
    parser.add_argument(
        "--scan-size",
        type=int,
        default=RADIATE_SCAN_SIZE,
        metavar="PX",
        help=f"side in pixels of the written scans, even (default {RADIATE_SCAN_SIZE}: RADIATE's)",
    )
    parser.add_argument("--clutter", type=float, default=1.0, help="clutter strength (1 = matched to real scans)")
    parser.add_argument("--ghosts", type=float, default=1.0, help="multipath ghost strength (1 = default)")
    parser.add_argument("--noise", type=float, default=1.0, help="noise floor power (1 = matched to real scans)")
    parser.add_argument(
        "--weather",
        choices=WEATHERS,
        help="the same drives, every one in this weather (default: drawn per drive, "
        + ", ".join(f"{100 * p:.0f}%% {w}" for w, p in zip(WEATHERS, WEATHER_PROBABILITIES))
        + "); with --realism, compare with real scans taken in that weather",
    )
    parser.add_argument(
        "--exact-labels",
        action="store_true",
        help="label every box with width across and yaw along its travel (default: RADIATE's "
        "annotators' 180-degree and width/length ambiguity)",
    )
    parser.add_argument(
        "--no-poses",
        action="store_true",
        help="write no ego_poses.csv, like a real RADIATE sequence (prepare with rafd odometry)",
    )
    parser.add_argument(
        "--polar", action="store_true", help="also write the polar scans (Navtech_Polar/, RADIATE's layout)"
    )
    parser.add_argument(
        "--realism",
        type=Path,
        nargs="+",
        metavar="REAL_SEQ",
        help="instead of writing: compare simulated scans with these real sequences' scans (no labels used) and print "
        "the realism table (rafd.sim.realism), one pair of columns per real root (e.g. RADIATE's tiny_foggy and the "
        "Oxford Radar RobotCar sample, read in its native layout)",
    )
    parser.add_argument(
        "--realism-sim",
        type=Path,
        metavar="ROOT",
        help="with --realism: take the simulated scans from this data root instead of simulating",
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="with --realism: also write the table as JSON here")
    parser.add_argument("--realism-steps", type=int, default=400, help="with --realism: classifier training steps")
    parser.add_argument(
        "--preview",
        action="store_true",
        help="instead of writing sequences: draw a simulated scan beside a real one into --out PNG",
    )
    parser.add_argument(
        "--sample",
        type=Path,
        metavar="REAL_SEQ",
        help="real RADIATE sequence for --preview (default $RAFD_RADIATE_SAMPLE)",
    )
    flags.add_quiet(parser)
    return parser


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    return _parser().parse_args(argv)


def _fail(message: str) -> int:
    print(f"rafd-simulate: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, simulate, print what was written; 0 on success, 2 on bad input."""
    args = parse(argv)
    flags.apply_quiet(args)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        difficulty = Difficulty(clutter=args.clutter, ghosts=args.ghosts, noise=args.noise)
    except ValueError as error:
        return _fail(str(error))
    if args.realism is not None:
        return _realism(args, difficulty)
    if args.preview:
        if args.out is None:
            return _fail("--preview needs --out FILE.png")
        sample = args.sample or (
            Path(os.environ["RAFD_RADIATE_SAMPLE"]) if os.environ.get("RAFD_RADIATE_SAMPLE") else None
        )
        if sample is None:
            return _fail("--preview needs a real sequence: pass --sample DIR or set RAFD_RADIATE_SAMPLE")
        if not (sample / "Navtech_Cartesian").is_dir():
            return _fail(f"{sample} is not a RADIATE sequence folder (needs Navtech_Cartesian/)")
        if not args.out.parent.is_dir():
            return _fail(f"folder of --out does not exist: {args.out.parent}")
        try:
            path = render_preview(args.out, sample, seed=args.seed, difficulty=difficulty)
        except OSError as error:
            return _fail(str(error))
        print(f"wrote {path}")
        return 0
    if args.out is None:
        return _fail("--out DIR is required (the folder receiving the sequences)")
    if args.sequences < 1:
        return _fail(f"--sequences must be >= 1, got {args.sequences}")
    if args.frames < 1:
        return _fail(f"--sequence-frames must be >= 1, got {args.frames}")
    if args.scan_size < 16 or args.scan_size % 2:
        return _fail(f"--scan-size must be an even number of pixels >= 16, got {args.scan_size}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        return _fail(f"cannot create --out {args.out}: {error}")
    if not os.access(args.out, os.W_OK | os.X_OK):
        return _fail(f"--out {args.out} is not writable")
    start = time.perf_counter()
    try:
        paths = simulate_dataset(
            args.out,
            args.sequences,
            args.frames,
            args.seed,
            flags.split_names(args.split) or "train_good_weather",
            args.scan_size,
            difficulty,
            ambiguous=not args.exact_labels,
            poses=not args.no_poses,
            polar=args.polar,
            weather=args.weather,
        )
    except OSError as error:
        return _fail(str(error))
    for path in paths:
        print(path)
    print(f"simulated {len(paths)} sequence(s) x {args.frames} frames in {time.perf_counter() - start:.1f} s")
    return 0


REALISM_DRIVES = 12  # simulated drives of --realism (3 frames each unless --sequence-frames is smaller)


def _sequences_of(root: Path) -> list[list]:
    """uint8 Cartesian scans of every sequence at or under `root` (polar-only folders converted), one list per
    sequence, in time order."""
    from rafd.data.dataset import find_sequences
    from rafd.data.reader import read_sequence

    return [
        [frame.load() for frame in read_sequence(folder, estimate_poses=False).frames]
        for folder in find_sequences(root)
    ]


def _realism(args: argparse.Namespace, difficulty: Difficulty) -> int:
    """Simulated vs real scans, label-free: one table (rafd.sim.realism)."""
    import json

    from rafd.sim.api import sequence_seed
    from rafd.sim.realism import format_table, format_tables, realism_table
    from rafd.sim.sequence import run_simulation

    if args.realism_sim is not None and args.weather is not None:
        return _fail(
            "--weather chooses the weather of the scans simulated here; --realism-sim reads scans already made"
        )
    try:
        references = {root.name: _sequences_of(root) for root in args.realism}
        if args.realism_sim is not None:
            simulated = _sequences_of(args.realism_sim)
        else:  # RADIATE-sized scans, a few consecutive frames from each of several drives
            simulated = [
                run_simulation(
                    sequence_seed(args.seed, k),
                    min(args.frames, 3),
                    "realism",
                    RADIATE_SCAN_SIZE,
                    difficulty,
                    name=f"realism_{k}",
                    weather=args.weather,
                ).images
                for k in range(args.sequences if args.sequences > 1 else REALISM_DRIVES)
            ]
    except (FileNotFoundError, ValueError) as error:
        return _fail(str(error))
    real = [scans for sequences in references.values() for scans in sequences]
    sizes = {scan.shape for scans in real + simulated for scan in scans}
    if sizes != {(RADIATE_SCAN_SIZE, RADIATE_SCAN_SIZE)}:
        return _fail(f"the realism measures compare {RADIATE_SCAN_SIZE} px RADIATE scans; got shapes {sorted(sizes)}")
    try:
        tables = {
            name: realism_table(sequences, simulated, seed=args.seed, classifier_steps=args.realism_steps)
            for name, sequences in references.items()
        }
    except ImportError:
        return _fail("the patch classifier needs torch: install the train extra")
    except ValueError as error:
        return _fail(str(error))
    counts = ", ".join(f"{sum(map(len, sequences))} real scans of {name}" for name, sequences in references.items())
    print(f"{counts}; {sum(map(len, simulated))} simulated scans")
    print(format_table(next(iter(tables.values()))) if len(tables) == 1 else format_tables(tables))
    if args.json is not None:
        payload = {name: [row.__dict__ for row in rows] for name, rows in tables.items()}
        args.json.write_text(json.dumps(payload if len(tables) > 1 else next(iter(payload.values())), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
