"""rafd label: label vehicles on a few scans of your own radar (docs/labelling.md has the protocol).

propose: per scan, DIR/<frame>_overview.png (the scan with its candidate returns numbered), one sheet per candidate
(DIR/<frame>_c<k>.png: previous, current and next scans around it, the neighbours moved into the current ego frame
so the static world stands still) and DIR/<frame>_candidates.txt (one line per candidate, in the box text format,
ready to keep, edit or delete).
apply: the boxes you kept (text, metres in the ego frame) -> RADIATE's annotation format keyed by scan timestamps.
render: every labelled scan with its boxes drawn, to check them.
compare: agreement of two label sets on the same scans: found / missed / extra (centres within 2 m), centre
distance and IoU of the matched boxes.
link: a sequence folder OUT that reads SEQ's scans (symlinks) with these labels and meta.json's split and labelled
area (outside it the scans are ignore regions), for rafd train / rafd eval.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from rafd.cli import flags
from rafd.data.candidates import propose
from rafd.data.frames import RadarSequence
from rafd.data.labels import IGNORE_CLASS, LABELLED_AREA_KEY, parse_box_lines, to_annotations, write_annotations
from rafd.data.mvdnet_labels import MVDNET_LABELS
from rafd.data.reader import read_sequence
from rafd.progress import track
from rafd.viz.labelling import candidate_sheet, into_frame, overview


def _frames(text: str | None, count: int) -> list[int]:
    """'1,3-5' -> [1, 3, 4, 5] (frame numbers), or every frame."""
    if not text:
        return list(range(1, count + 1))
    numbers: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        numbers += list(range(int(first), int(last or first) + 1))
    return numbers


def _timestamp_us(text: str) -> int:
    seconds, fraction = text.split(".")
    return int(seconds) * 1_000_000 + int(fraction) // 1000


def run_propose(args: argparse.Namespace) -> int:
    sequence = read_sequence(args.sequence, estimate_poses=True)
    args.out.mkdir(parents=True, exist_ok=True)
    assert sequence.poses is not None
    for number in track(_frames(args.frame_numbers, len(sequence)), desc="propose", unit="scan"):
        k = sequence.frame_index(number)
        current = sequence.load_image(k)
        neighbours = [
            into_frame(sequence.load_image(j), sequence.poses[j], sequence.poses[k], sequence.resolution)
            if 0 <= j < len(sequence)
            else None
            for j in (k - 1, k + 1)
        ]
        candidates = propose(current, sequence.resolution, args.radius)
        stamp = _timestamp_us(sequence.frames[k].timestamp_text) if sequence.frames[k].timestamp_text else number
        name = f"{number:06d}"
        cv2.imwrite(str(args.out / f"{name}_overview.png"), overview(current, candidates, half_m=args.radius))
        for candidate in candidates:
            sheet = candidate_sheet(
                [neighbours[0], current, neighbours[1]],
                candidate,
                ["previous (in this frame)", f"current: frame {number}", "next (in this frame)"],
            )
            cv2.imwrite(str(args.out / f"{name}_c{candidate.index:02d}.png"), sheet)
        lines = [
            f"# frame {number}: {len(candidates)} candidates; keep the vehicles, set the track id and class, fix "
            "the box, delete the rest\n# timestamp track class x y width length yaw_deg"
        ]
        lines += [
            f"{stamp} {c.index} car {c.x:.2f} {c.y:.2f} {c.width:.2f} {c.length:.2f} {c.yaw_deg:.1f}"
            for c in candidates
        ]
        (args.out / f"{name}_candidates.txt").write_text("\n".join(lines) + "\n")
        print(f"frame {number}: {len(candidates)} candidates -> {args.out / (name + '_overview.png')}")
    return 0


def run_apply(args: argparse.Namespace) -> int:
    boxes = parse_box_lines(args.boxes.read_text().splitlines(), str(args.boxes))
    sequence = read_sequence(args.sequence, estimate_poses=False)
    known = {_timestamp_us(f.timestamp_text) for f in sequence.frames}
    unknown = sorted({b.timestamp_us for b in boxes} - known)
    if unknown:
        raise ValueError(f"{args.boxes}: {len(unknown)} timestamps are no scan of {args.sequence} (first {unknown[0]})")
    write_annotations(args.out, to_annotations(boxes, sequence.image_size, sequence.resolution))
    tracks = {b.track for b in boxes if b.class_name != IGNORE_CLASS}
    print(
        f"{args.out}: {sum(b.class_name != IGNORE_CLASS for b in boxes)} vehicle boxes in {len(tracks)} tracks, "
        f"{sum(b.class_name == IGNORE_CLASS for b in boxes)} ignore regions"
    )
    return 0


@contextlib.contextmanager
def _labelled(sequence_dir: Path, labels: Path) -> Iterator[RadarSequence]:
    """The sequence read with `labels` as its annotations: a label file (JSON), or a folder of MVDNet label_2d files
    (through a linked folder in a temporary place, removed on leaving: the frames read their scans through it)."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="rafd-label-") as tmp:
        work = Path(tmp) / sequence_dir.name
        if labels.is_dir():
            link_folder(sequence_dir, None, work, None)
            os.symlink(labels.resolve(), work / MVDNET_LABELS)
        else:
            link_folder(sequence_dir, labels, work, None)
        yield read_sequence(work, estimate_poses=False)


def run_render(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    with _labelled(args.sequence, args.labels) as sequence:
        for frame in track(sequence.frames, desc="render", unit="scan"):
            if not frame.objects:
                continue
            boxes = np.stack([o.box for o in frame.objects])
            image = overview(frame.load(), [], boxes, [o.class_name for o in frame.objects], half_m=args.radius)
            cv2.imwrite(str(args.out / f"{frame.number:06d}_labels.png"), image)
    print(f"drew the labelled scans into {args.out}")
    return 0


def agreement(
    reference: list[np.ndarray],
    candidate: list[np.ndarray],
    ignore: list[np.ndarray] | None = None,
    distance_m: float = 2.0,
) -> dict[str, float]:
    """Per scan [M, 5] boxes of two labellers -> found / missed / extra (greedy nearest centres within distance_m),
    the reference boxes that fall in the candidate's ignore regions (neither found nor missed), and the mean centre
    distance and IoU of the matched pairs."""
    from rafd.eval.metrics import rotated_iou
    from rafd.geometry import points_in_boxes

    found = missed = extra = ignored = 0
    distances, ious = [], []
    for k, (ref, cand) in enumerate(zip(reference, candidate)):
        regions = ignore[k] if ignore is not None else np.zeros((0, 5))
        used = np.zeros(len(cand), bool)
        for box in ref:
            d = np.hypot(*(cand[:, :2] - box[:2]).T) if len(cand) else np.zeros(0)
            d[used] = np.inf
            j = int(np.argmin(d)) if len(d) else -1
            if j < 0 or d[j] > distance_m:
                if len(regions) and points_in_boxes(box[None, :2], regions).any():
                    ignored += 1
                else:
                    missed += 1
                continue
            used[j] = True
            found += 1
            distances.append(float(d[j]))
            ious.append(float(rotated_iou(box[None], cand[j][None])[0, 0]))
        extra += int((~used).sum())
    return {
        "reference": found + missed + ignored,
        "found": found,
        "missed": missed,
        "in_ignore": ignored,
        "extra": extra,
        "distance_m": distance_m,
        "centre_distance_mean_m": float(np.mean(distances)) if distances else float("nan"),
        "iou_mean": float(np.mean(ious)) if ious else float("nan"),
    }


def run_compare(args: argparse.Namespace) -> int:
    def boxes(sequence: RadarSequence, keep_ignore: bool) -> list[np.ndarray]:
        return [
            np.array([o.box for o in f.objects if (o.class_name == IGNORE_CLASS) == keep_ignore]).reshape(-1, 5)
            for f in sequence.frames
        ]

    with _labelled(args.sequence, args.reference) as reference, _labelled(args.sequence, args.candidate) as candidate:
        expected, found, ignored = boxes(reference, False), boxes(candidate, False), boxes(candidate, True)
    for distance in args.distance:
        result = agreement(expected, found, ignored, distance)
        print(json.dumps(result))
    return 0


def link_folder(
    sequence_dir: Path,
    labels: Path | None,
    out: Path,
    split: str | None,
    frames: list[int] | None = None,
    labelled_half_m: float | None = None,
) -> Path:
    """A sequence folder at `out` reading `sequence_dir`'s native scans through symlinks, with `labels` as its
    annotations and `split` in its meta.json; `frames` keeps only those scans (numbers in time order);
    `labelled_half_m`: the labelled square, outside which the datasets ignore the scans (rafd.data.labels)."""
    from rafd.ros.sequence import is_bag

    if is_bag(sequence_dir):
        raise ValueError(
            f"{sequence_dir} is a ROS 2 bag: link, render and compare read a folder's scan files; write the bag's "
            "scans as a folder first (rafd polar BAG --out DIR), or propose and apply on the bag itself"
        )
    sequence_dir, out = sequence_dir.resolve(), Path(out)
    (out / "radar").mkdir(parents=True, exist_ok=True)
    source = read_sequence(sequence_dir, estimate_poses=False)
    chosen = [f for f in source.frames if frames is None or f.number in frames]
    for frame in chosen:
        target = out / "radar" / frame.image_path.name
        if not target.exists():
            os.symlink(frame.image_path.resolve(), target)
    (out / "radar.timestamps").write_text("".join(f"{_timestamp_us(f.timestamp_text)} 1\n" for f in chosen))
    ground_truth = sequence_dir / "gt" / "radar_odometry.csv"
    if ground_truth.is_file():
        (out / "gt").mkdir(exist_ok=True)
        if not (out / "gt" / "radar_odometry.csv").exists():
            os.symlink(ground_truth, out / "gt" / "radar_odometry.csv")
    if labels is not None:
        (out / "annotations").mkdir(exist_ok=True)
        (out / "annotations" / "annotations.json").write_text(Path(labels).read_text())
    meta: dict[str, str | float] = {"name": out.name, "native_format": "oxford"}
    if split is not None:
        meta["set"] = split
    if labelled_half_m:
        meta[LABELLED_AREA_KEY] = labelled_half_m
    (out / "meta.json").write_text(json.dumps(meta))
    return out


def run_link(args: argparse.Namespace) -> int:
    names = flags.split_names(args.split)
    if len(names) != 1:
        raise ValueError(f"link writes one split: give --split once with one name, got {list(names)}")
    split = names[0]
    if args.labelled_half_m < 0:
        raise ValueError(f"--labelled-half-m must be >= 0 metres, got {args.labelled_half_m}")
    frames = _frames(args.frame_numbers, 10**6) if args.frame_numbers else None
    out = link_folder(args.sequence, args.labels, args.out, split, frames, args.labelled_half_m)
    area = f", labelled within {args.labelled_half_m:g} m" if args.labelled_half_m else ""
    print(f"{out}: {len(read_sequence(out, estimate_poses=False))} scans, split {split}{area}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("label"),
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("propose", help="candidate returns and their sheets for each scan")
    p.add_argument("sequence", type=Path, help="sequence folder (RADIATE, polar-only or native) or a ROS 2 bag")
    flags.add_out(p, "DIR", "folder for the pictures and the candidate lists", required=True)
    p.add_argument("--frame-numbers", metavar="LIST", help="frame numbers, e.g. 1,3-5 (default: all)")
    p.add_argument("--radius", type=float, default=40.0, help="metres around the radar to propose in")
    flags.add_quiet(p)
    a = commands.add_parser("apply", help="box text -> a label file")
    a.add_argument(
        "sequence", type=Path, help="the labelled sequence folder (RADIATE, polar-only or native) or a ROS 2 bag"
    )
    a.add_argument("boxes", type=Path, help="text: timestamp track class x y width length yaw_deg per line")
    flags.add_out(a, "JSON", "label file to write", required=True)
    r = commands.add_parser("render", help="draw a label file's boxes on its scans")
    r.add_argument("sequence", type=Path, help="the labelled sequence folder")
    r.add_argument("labels", type=Path, help="label file (JSON, rafd label apply)")
    flags.add_out(r, "DIR", "folder for the pictures", required=True)
    r.add_argument("--radius", type=float, default=40.0, help="metres around the radar to draw")
    flags.add_quiet(r)
    c = commands.add_parser("compare", help="agreement of two label files on the same scans")
    c.add_argument("reference", type=Path, help="label file (JSON), or a folder of MVDNet label_2d files")
    c.add_argument("candidate", type=Path, help="the same, whose ignore regions excuse misses")
    c.add_argument("sequence", type=Path, help="the sequence folder both label sets describe")
    c.add_argument(
        "--distance",
        type=float,
        nargs="+",
        default=[2.0],
        help="centre distances (m) that count as the same vehicle (one result line each)",
    )
    k = commands.add_parser("link", help="a labelled sequence folder over a native folder's scans")
    k.add_argument("sequence", type=Path, help="the native (or RADIATE) folder holding the scans")
    k.add_argument("labels", type=Path, help="label file (JSON, rafd label apply)")
    k.add_argument("out", type=Path, metavar="OUT", help="the sequence folder to write")
    flags.add_split(k, "the meta.json set of the written folder, e.g. train or val (one name)", required=True)
    k.add_argument("--frame-numbers", metavar="LIST", help="frame numbers to keep, e.g. 1-11 (default: all)")
    k.add_argument(
        "--labelled-half-m",
        type=float,
        default=30.0,
        metavar="M",
        help="the square |x|, |y| <= M around the radar holds every vehicle's label (default %(default)s: the "
        "protocol's); training and evaluation ignore the scans outside it (0: no such square)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser, args = flags.parse(build_parser, argv)
    run = {"propose": run_propose, "apply": run_apply, "render": run_render, "compare": run_compare, "link": run_link}[
        args.command
    ]
    try:
        return run(args)
    except (FileNotFoundError, ValueError) as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
