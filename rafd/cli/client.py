"""`rafd-client SEQ_DIR --url URL [--out DIR]`: stream a RADIATE-format sequence to a running rafd-serve.

Posts every radar frame in timestamp order (with its pose from ego_poses.csv when present, else the
service estimates ego motion), then writes each frame with its boxes and flow drawn, the answers as
JSON lines, and an MP4 of the whole sequence. Uses only the standard library for HTTP.
"""
from __future__ import annotations

import argparse
import base64
import json
import sys
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np


@dataclass(frozen=True)
class ClientFrame:
    number: int
    timestamp: float
    image_path: Path
    pose: np.ndarray | None  # [3] world pose, None to let the service use odometry


def read_frames(sequence_dir: Path) -> tuple[str, list[ClientFrame]]:
    """(sequence name, frames sorted by timestamp); poses only from the folder's ego_poses.csv.

    No odometry here: without a pose file the service estimates ego motion itself (and says so).
    """
    from rafd.data import read_sequence

    sequence = read_sequence(sequence_dir, estimate_poses=False)
    frames = [
        ClientFrame(f.number, float(f.timestamp), Path(f.image_path),
                    None if sequence.poses is None else sequence.poses[i])
        for i, f in enumerate(sequence.frames)
    ]
    return sequence.name or sequence_dir.name, sorted(frames, key=lambda f: f.timestamp)


class ServiceError(RuntimeError):
    pass


def post_frame(url: str, stream_id: str, frame: ClientFrame, use_pose: bool, timeout: float) -> dict[str, Any]:
    """One POST /detect with the PNG file's bytes as they are on disk."""
    body: dict[str, Any] = {
        "stream_id": stream_id,
        "timestamp": frame.timestamp,
        "image": base64.b64encode(frame.image_path.read_bytes()).decode("ascii"),
    }
    if use_pose and frame.pose is not None:
        body["pose"] = {"x": float(frame.pose[0]), "y": float(frame.pose[1]), "yaw": float(frame.pose[2])}
    request = urllib.request.Request(f"{url.rstrip('/')}/detect", data=json.dumps(body).encode(),
                                     headers={"content-type": "application/json"}, method="POST")
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return json.loads(response.read())
    except urllib.error.HTTPError as exc:
        try:
            reason = json.loads(exc.read())["error"]["message"]
        except (ValueError, KeyError, TypeError):
            reason = exc.reason
        raise ServiceError(f"frame {frame.number}: HTTP {exc.code}: {reason}") from exc
    except urllib.error.URLError as exc:
        raise ServiceError(f"cannot reach {url}: {exc.reason}") from exc


def draw_answer(image: np.ndarray, answer: dict[str, Any], flow_scale: float, flow_step: int) -> np.ndarray:
    """Grey scan [H, W] -> BGR [H, W, 3] with the model crop, flow arrows (cyan) and boxes (green)."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    crop = answer["input"]
    top_left = crop["crop_offset_px"]
    bottom_right = top_left + crop["model_size"] - 1
    cv2.rectangle(canvas, (top_left, top_left), (bottom_right, bottom_right), (80, 80, 80), 1)
    flow = answer.get("flow")
    if flow and flow["encoding"] == "list":
        values = np.asarray(flow["values"])  # [2, Hf, Wf] metres, x right / y forward
        grid = flow["grid"]
        metres_per_px = grid["cell_size_m"] / grid["stride_px"]
        for i in range(0, grid["height"], flow_step):
            for j in range(0, grid["width"], flow_step):
                dx, dy = values[0, i, j], values[1, i, j]
                if np.hypot(dx, dy) < 0.05:  # below 5 cm: nothing moved
                    continue
                u = grid["origin_px"][0] + (j + 0.5) * grid["stride_px"]
                v = grid["origin_px"][1] + (i + 0.5) * grid["stride_px"]
                end = (u + flow_scale * dx / metres_per_px, v - flow_scale * dy / metres_per_px)  # y forward = up
                cv2.arrowedLine(canvas, (round(u), round(v)), (round(end[0]), round(end[1])), (255, 255, 0), 1,
                                tipLength=0.3)
    for box in answer["boxes"]:
        polygon = np.round(np.asarray(box["polygon"])).astype(np.int32)  # [4, 2] posted pixels
        cv2.polylines(canvas, [polygon], True, (0, 255, 0), 1)
        cv2.putText(canvas, f"{box['score']:.2f}", tuple(polygon[0]), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 255, 0), 1)
    status = f"frames {answer['frames_used']}/{answer['num_frames']} pose {answer['pose_source']} " \
             f"{len(answer['boxes'])} boxes {answer['timing']['model_ms']:.0f} ms"
    cv2.putText(canvas, status, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 200, 255), 1)
    return canvas


def frame_rate(frames: list[ClientFrame]) -> float:
    """The sequence's own rate (Navtech: 4 Hz), from the median timestamp step."""
    if len(frames) < 2:
        return 4.0
    step = float(np.median(np.diff([f.timestamp for f in frames])))
    return 1.0 / step if step > 0 else 4.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-client", description=__doc__.splitlines()[0])
    parser.add_argument("sequence", type=Path, help="RADIATE-format sequence folder (Navtech_Cartesian/ + .txt)")
    parser.add_argument("--url", required=True, help="service base URL, e.g. http://127.0.0.1:8000")
    parser.add_argument("--out", type=Path, default=None, help="where to write frames/, answers.jsonl, sequence.mp4")
    parser.add_argument("--stream-id", default=None, help="stream id (default: the sequence name)")
    parser.add_argument("--no-pose", action="store_true", help="do not send ego_poses.csv: the service uses odometry")
    parser.add_argument("--limit", type=int, default=None, help="only the first N frames")
    parser.add_argument("--flow-scale", type=float, default=3.0, help="arrow length multiplier for the flow")
    parser.add_argument("--flow-step", type=int, default=2, help="draw every n-th flow cell")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds per request")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        name, frames = read_frames(args.sequence)
    except (OSError, ValueError) as exc:
        print(f"rafd-client: {exc}", file=sys.stderr)
        return 2
    frames = frames[: args.limit] if args.limit else frames
    if not frames:
        print(f"rafd-client: {args.sequence} holds no radar frames", file=sys.stderr)
        return 2
    stream_id = args.stream_id or "".join(c if c.isalnum() or c in "._-" else "_" for c in name)[:128]
    out = args.out
    writer = None
    answers = None
    if out is not None:
        (out / "frames").mkdir(parents=True, exist_ok=True)
        answers = (out / "answers.jsonl").open("w")
    try:
        for frame in frames:
            answer = post_frame(args.url, stream_id, frame, not args.no_pose, args.timeout)
            print(f"frame {frame.number:06d} t={frame.timestamp:.3f}: {len(answer['boxes'])} boxes, "
                  f"frames_used {answer['frames_used']}, pose {answer['pose_source']}, "
                  f"{answer['timing']['total_ms']:.1f} ms")
            if out is None:
                continue
            answers.write(json.dumps(answer) + "\n")
            image = cv2.imread(str(frame.image_path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise ServiceError(f"cannot read {frame.image_path}")
            canvas = draw_answer(image, answer, args.flow_scale, args.flow_step)
            cv2.imwrite(str(out / "frames" / f"{frame.number:06d}.png"), canvas)
            if writer is None:
                size = (canvas.shape[1], canvas.shape[0])
                writer = cv2.VideoWriter(str(out / "sequence.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                                         frame_rate(frames), size)
            writer.write(canvas)
    except (ServiceError, OSError) as exc:
        print(f"rafd-client: {exc}", file=sys.stderr)
        return 1
    finally:
        if writer is not None:
            writer.release()
        if answers is not None:
            answers.close()
    if out is not None:
        print(f"wrote {len(frames)} frames, answers.jsonl and sequence.mp4 to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
