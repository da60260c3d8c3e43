"""rafd client: stream a RADIATE-format sequence, or a ROS 2 bag's radar scans, to a running rafd serve.

Posts every radar frame in timestamp order (with its pose from ego_poses.csv when present, else the
service estimates ego motion). A folder with only the sensor's polar scans (Navtech_Polar/) posts them as
they are (the service converts them with the same rafd.scans.polar conversion the client draws and logs), or
converted first when meta.json asks for another size or resolution. With --out: each frame's picture
(rafd.viz.answer: what was detected over, predictions with scores, ground truth where labelled, flow,
legend), the answers as JSON lines and an MP4. With --mcap: a Foxglove/MCAP log of scans, poses, boxes, flow and
ground truth (rafd.viz.mcap, `logs` extra). Uses only the standard library for HTTP.

ROS 2 (`ros` extra, docs/ros2.md): a bag (a rosbag2 folder, its .mcap or .db3 file, or a ROS 1 .bag) posts its scan
topic's scans (Navtech's RadarBScanMsg, or Image / CompressedImage; found by type, or --topic) as native scans with
the range bin of the bag's RadarConfigurationMsg (else --range-resolution), each at its header stamp. --bag-out OUT
writes the answers as a ROS 2 bag: Detection3DArray on /rafd/detections, RadarTracks on /rafd/tracks, Odometry on
/rafd/odometry and /tf per scan (REP-103 axes), the scan and the flow on request (--bag-scan, --bag-flow); the bag
is complete or absent.

Every run starts its stream fresh, so a run repeats: by default each run posts to a new stream, named after the
sequence plus a short run id (`tiny_foggy-3fa9c2`); `--stream-id ID` names the stream yourself, and `--reset`
deletes that stream on the service first (a second run with the same --stream-id and no --reset is refused with
409: the service already holds later timestamps of that stream).

Failover: every frame names the previous frame the client got an answer for (`previous_timestamp`), so a replica
whose chain of the stream is another one restarts it instead of stacking the frame on stale frames. A frame whose
answer is lost (502 / 503 / 504, a connection error or a timeout: a replica died or restarted) is posted again, up to
--retries times with exponential backoff (0.25 s doubling, at most 4 s, or the Retry-After header's seconds when
longer, up to 4 s); the replica that answered it answers the same again, and another one takes it as a new frame.
Each retry is logged on stderr and counted in the closing summary.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import http.client
import json
import os
import secrets
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from rafd import progress
from rafd.cli import flags
from rafd.data.frames import RadarFrame
from rafd.detect_client import (
    FrameFields,
    api_key_header,
    base64_png,
    detect_request,
    json_body,
    png_bytes,
    pose_of,
    post,
    stream_header,
)
from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.protocol import STREAM_ID_MAX_LENGTH, stream_id_from
from rafd.scans.cartesian import png_size
from rafd.scans.native import NativeSource
from rafd.scans.polar import RADIATE_AZIMUTHS, RADIATE_RANGE_BINS

if TYPE_CHECKING:
    from rafd.ros.scans import BagScan, RadarGeometry


def _is_radiate_polar_png(path: Path) -> bool:
    """Whether the file is a PNG of RADIATE's polar shape (posted as it is); any other file is posted converted."""
    try:
        return png_size(path) == (RADIATE_AZIMUTHS, RADIATE_RANGE_BINS)
    except ValueError:  # not a PNG
        return False


@dataclass(frozen=True)
class ClientFrame:
    number: int
    timestamp: float
    source: RadarFrame  # the reader's frame: its scan (Cartesian, or polar converted on load) and labels
    pose: np.ndarray | None  # [3] world pose, None to let the service use odometry
    range_resolution_m: float | None = None  # a bag's native scan: its configuration's range bin, posted with it

    def scan_and_png(self) -> tuple[np.ndarray, bytes]:
        """(uint8 [N, N] Cartesian scan, its PNG bytes): a Cartesian PNG as it is on disk, a polar scan converted."""
        scan = self.source.load()
        if self.source.polar is None:
            return scan, self.source.image_path.read_bytes()
        return scan, png_bytes(scan)

    def posted_png(self, scan_png: bytes) -> bytes:
        """The PNG to post: a RADIATE polar scan or a native scan (Oxford, Boreas) as it is on disk when it was
        converted to RADIATE's own grid (the service converts it the same way, and the answer's pixels are that
        grid's); else the scan's PNG."""
        source = self.source.polar
        if source is None or source.size != RADIATE_SCAN_SIZE or source.resolution != RADIATE_RESOLUTION:
            return scan_png
        if isinstance(source, NativeSource) or _is_radiate_polar_png(self.source.image_path):
            return self.source.image_path.read_bytes()
        return scan_png


@dataclass(frozen=True)
class BagFrameInput:
    """A bag's scan as the client posts it: the scan's PNG (native or RADIATE polar, as the service reads it) and its
    range bin; the Cartesian scan made only when something draws it."""

    scan: BagScan

    def posted_png(self) -> bytes:
        return png_bytes(self.scan.pixels)

    def cartesian(self) -> np.ndarray:
        from rafd.ros.sequence import cartesian_of

        return cartesian_of(self.scan)


@dataclass(frozen=True)
class ClientSequence:
    name: str
    resolution: float
    annotated: bool  # the folder has annotations/annotations.json: draw and log ground truth
    frames: list[ClientFrame]  # sorted by timestamp
    bag: Any = None  # rafd.ros.reader.BagTopic when the sequence is a bag's scan topic


def read_bag_frames(bag: Path, topic: str | None, flags: RadarGeometry | None) -> ClientSequence:
    """A bag's scan topic as the client's frames (no pose: the service estimates ego motion)."""
    from rafd.data.reader import read_bag_sequence
    from rafd.ros.sequence import BagScanSource, bag_frames

    found, listed = bag_frames(bag, topic, flags)
    sequence = read_bag_sequence(bag, estimate_poses=False)  # its name, frames' texts and BAG.ego_poses.csv
    frames = []
    for k, ((log, stamp), frame) in enumerate(zip(listed, sequence.frames)):
        source = RadarFrame(
            frame.number, frame.timestamp, bag, [], BagScanSource(found, log, stamp), frame.timestamp_text
        )
        pose = None if sequence.poses is None else sequence.poses[k]
        frames.append(ClientFrame(frame.number, frame.timestamp, source, pose))
    return ClientSequence(sequence.name, RADIATE_RESOLUTION, False, frames, found)


def bag_inputs(sequence: ClientSequence, frames: list[ClientFrame]) -> Any:
    """BagFrameInput per frame of a bag, read in one pass over its scan topic (one message held at a time); None for
    a folder."""
    if sequence.bag is None:
        return None
    from rafd.ros.reader import read_scans

    scans = read_scans(sequence.bag)

    def each() -> Any:
        for frame in frames:
            _, scan = next(scans)
            if scan.stamp_ns != frame.source.timestamp_ns:
                raise ValueError(
                    f"{sequence.bag.path}: the scan stamped {scan.stamp_ns} ns is not frame {frame.number}"
                )
            yield BagFrameInput(scan)

    return each()


def read_frames(sequence_dir: Path) -> ClientSequence:
    """Frames sorted by timestamp; poses only from the folder's ego_poses.csv.

    No odometry here: without a pose file the service estimates ego motion itself (and says so).
    """
    from rafd.data import read_sequence

    sequence = read_sequence(sequence_dir, estimate_poses=False)
    frames = [
        ClientFrame(f.number, float(f.timestamp), f, None if sequence.poses is None else sequence.poses[i])
        for i, f in enumerate(sequence.frames)
    ]
    return ClientSequence(
        sequence.name or sequence_dir.name,
        sequence.resolution,
        sequence.annotated,
        sorted(frames, key=lambda f: f.timestamp),
    )


class ServiceError(RuntimeError):
    def __init__(self, message: str, code: str | None = None) -> None:
        super().__init__(message)
        self.code = code  # the service's error code, when it answered one


RUN_ID_HEX = 6  # characters of the run id appended to the sequence name


def new_stream_id(sequence_name: str) -> str:
    """The stream of one run: the sequence's name (characters a stream id may not hold replaced) plus a fresh run
    id, so running the same sequence again starts a new stream instead of colliding with the last run's."""
    run_id = secrets.token_hex(RUN_ID_HEX // 2)
    return stream_id_from(sequence_name)[: STREAM_ID_MAX_LENGTH - RUN_ID_HEX - 1] + "-" + run_id


def _error_of(exc: urllib.error.HTTPError) -> tuple[str | None, str]:
    """(code, message) of a service error answer; (None, the HTTP reason) when the body is not one."""
    try:
        error = json.loads(exc.read())["error"]
        return str(error["code"]), str(error["message"])
    except (ValueError, KeyError, TypeError):
        return None, str(exc.reason)


def reset_stream(url: str, stream_id: str, timeout: float, api_key: str | None = None) -> bool:
    """DELETE /streams/{id}: True when the service held the stream, False when it did not (404); ServiceError else."""
    request = urllib.request.Request(
        f"{url.rstrip('/')}/streams/{urllib.parse.quote(stream_id, safe='')}",
        headers={**api_key_header(api_key), **stream_header(stream_id)},
        method="DELETE",
    )
    try:
        with urllib.request.urlopen(request, timeout=timeout):
            return True
    except urllib.error.HTTPError as exc:
        code, message = _error_of(exc)
        if exc.code == 404 and code == "stream_not_found":
            return False
        raise ServiceError(f"--reset: DELETE /streams/{stream_id}: HTTP {exc.code}: {message}", code) from exc
    except urllib.error.URLError as exc:
        raise ServiceError(f"cannot reach {url}: {exc.reason}") from exc


# Answers of a router or of a replica going away, where the frame may not have been used: safe to post again (the
# service answers a repeated frame with its first answer, or takes it as new where it never arrived).
RETRY_STATUSES = frozenset({502, 503, 504})
RETRY_FIRST_S = 0.25
RETRY_MAX_S = 4.0


class RetryableError(ServiceError):
    """A failure after which the same frame may be posted again."""

    def __init__(self, message: str, code: str | None = None, retry_after_s: float | None = None) -> None:
        super().__init__(message, code)
        self.retry_after_s = retry_after_s


def _retry_after(exc: urllib.error.HTTPError) -> float | None:
    try:
        return float(exc.headers.get("Retry-After", ""))
    except (TypeError, ValueError):
        return None


def retry_delay(attempt: int, retry_after_s: float | None = None) -> float:
    """Seconds before retry `attempt` (1, 2, ...): 0.25 s doubling, at most RETRY_MAX_S; a longer Retry-After wins,
    still bounded."""
    delay = min(RETRY_MAX_S, RETRY_FIRST_S * 2 ** (attempt - 1))
    if retry_after_s is not None and retry_after_s > delay:
        delay = min(RETRY_MAX_S, retry_after_s)
    return delay


def post_frame(
    url: str,
    stream_id: str,
    frame: ClientFrame,
    png: bytes,
    use_pose: bool,
    timeout: float,
    api_key: str | None = None,
    previous_timestamp: float | None = None,
) -> dict[str, Any]:
    """One POST /detect (JSON body, base64 PNG); `api_key` goes in the X-API-Key header the service checks, the
    stream id in the X-Stream-Id header as well as in the body; `previous_timestamp`: the stream's previous frame
    that was answered (the service restarts a chain that does not end there). RetryableError when the frame may be
    posted again (502 / 503 / 504, a connection error, a timeout)."""
    pose = pose_of(frame.pose) if use_pose and frame.pose is not None else None
    range_bin = getattr(frame, "range_resolution_m", None)  # a ClientFrame; stand-ins without it post none
    fields = FrameFields(frame.timestamp, stream_id, pose, previous_timestamp, range_bin)
    request = detect_request(json_body(fields, base64_png(png)), header_stream_id=stream_id, api_key=api_key)
    try:
        with post(url, request, timeout) as response:
            return json.loads(response.read())
    except urllib.error.HTTPError as exc:
        code, reason = _error_of(exc)
        message = f"frame {frame.number}: HTTP {exc.code}: {reason}"
        if exc.code in RETRY_STATUSES:
            raise RetryableError(message, code, _retry_after(exc)) from exc
        raise ServiceError(message, code) from exc
    except urllib.error.URLError as exc:
        raise RetryableError(f"cannot reach {url}: {exc.reason}") from exc
    except (ConnectionError, TimeoutError, http.client.HTTPException) as exc:  # the connection broke mid-answer
        raise RetryableError(f"frame {frame.number}: connection lost: {type(exc).__name__}: {exc}") from exc


def post_with_retries(
    retries: int,
    post: Any,
    describe: str,
    log: Any = None,
    sleep: Any = time.sleep,
) -> tuple[dict[str, Any], int]:
    """`post()` until it answers, at most `retries` more times after a RetryableError (backoff between); -> (answer,
    retries used). The last error is raised when every attempt failed. `log(line)` gets one line per retry."""
    log = log or (lambda line: print(line, file=sys.stderr))
    for attempt in range(retries + 1):
        try:
            return post(), attempt
        except RetryableError as exc:
            if attempt == retries:
                raise ServiceError(f"{exc} (after {retries} retries)", exc.code) from exc
            delay = retry_delay(attempt + 1, exc.retry_after_s)
            log(f"rafd-client: {describe}: {exc}; retry {attempt + 1} of {retries} in {delay:.2f} s")
            sleep(delay)
    raise AssertionError("unreachable")  # the loop returns or raises


def truth_polygons(frame: ClientFrame, annotated: bool) -> np.ndarray | None:
    """[M, 4, 2] ground-truth corners in the scan's pixels; None for an unlabelled folder."""
    if not annotated:
        return None
    return np.array([o.polygon for o in frame.source.objects], dtype=np.float64).reshape(-1, 4, 2)


def logged_frame(
    frame: ClientFrame,
    scan: np.ndarray,
    png: bytes,
    answer: dict[str, Any],
    resolution: float,
    annotated: bool,
    validity: np.ndarray | None = None,
):
    """One answer -> rafd.viz.mcap.LoggedFrame (boxes, polygons and flow as the service answered them; flow only in
    the cells `validity` marks valid, when given)."""
    from rafd.viz.mcap import frame_from_answer

    covered = answer["input"]["covered"]  # the square detected over
    offset, side = covered["offset_px"], covered["side_px"]
    truth = None
    if annotated:
        truth = np.array([o.box for o in frame.source.objects], dtype=np.float64).reshape(-1, 5)
    return frame_from_answer(
        answer,
        png,
        scan.shape[0],
        resolution,
        scan[offset : offset + side, offset : offset + side],
        frame.source.timestamp_ns,
        truth_boxes=truth,
        truth_polygons=truth_polygons(frame, annotated),
        validity=validity,
    )


def frame_rate(frames: list[ClientFrame]) -> float:
    """The sequence's own rate (Navtech: 4 Hz), from the median timestamp step."""
    if len(frames) < 2:
        return 4.0
    step = float(np.median(np.diff([f.timestamp for f in frames])))
    return 1.0 / step if step > 0 else 4.0


def read_sequence_or_bag(args: argparse.Namespace) -> ClientSequence:
    """The frames of SEQ_DIR_OR_BAG: a bag's scan topic (rafd.ros), else the folder's frames."""
    from rafd.ros.sequence import is_bag

    if is_bag(args.sequence):
        try:
            from rafd.ros.scans import RadarGeometry
        except ImportError as exc:  # pragma: no cover - the ros extra is missing
            raise ValueError(f"reading a bag needs the ros extra (pip install 'rafd[ros]'): {exc}") from exc
        geometry = None if args.range_resolution is None else RadarGeometry(range_bin_m=args.range_resolution)
        return read_bag_frames(args.sequence, args.topic, geometry)
    if args.topic is not None or args.range_resolution is not None:
        raise ValueError(f"--topic and --range-resolution read a bag; {args.sequence} is not one")
    return read_frames(args.sequence)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("client"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "sequence",
        type=Path,
        metavar="SEQ_DIR_OR_BAG",
        help="RADIATE-format sequence folder (Navtech_Cartesian/ + .txt, Navtech_Polar/ + .txt, or native radar/), or "
        "a ROS 2 bag (rosbag2 folder, .mcap, .db3; ROS 1 .bag)",
    )
    parser.add_argument("--url", required=True, help="service base URL, e.g. http://127.0.0.1:8000")
    flags.add_out(parser, "DIR", "folder receiving frames/ (one picture per answer), answers.jsonl and sequence.mp4")
    parser.add_argument(
        "--mcap", type=Path, default=None, metavar="FILE", help="write a Foxglove/MCAP log of the run to this file"
    )
    parser.add_argument(
        "--stream-id",
        default=None,
        metavar="ID",
        help="post to this stream (default: a new stream per run, the sequence name plus a run id)",
    )
    parser.add_argument(
        "--reset",
        action="store_true",
        help="delete the stream on the service first (DELETE /streams/ID), so a run with the same --stream-id repeats",
    )
    parser.add_argument("--no-pose", action="store_true", help="do not send ego_poses.csv: the service uses odometry")
    parser.add_argument("--limit", type=int, default=None, metavar="N", help="only the first N frames")
    parser.add_argument(
        "--flow-scale",
        type=float,
        default=None,
        help="draw flow arrows this many times their true length (default: 1, or more when zoomed out)",
    )
    parser.add_argument("--flow-step", type=int, default=2, help="draw every n-th flow cell (default 2)")
    parser.add_argument(
        "--view", type=int, default=768, metavar="PX", help="side in pixels of the zoomed model view (default 768)"
    )
    bag = parser.add_argument_group("ROS 2 bags (docs/ros2.md; the ros extra)")
    bag.add_argument("--topic", help="the bag's scan topic (default: the one topic of a scan type)")
    bag.add_argument(
        "--range-resolution",
        type=float,
        metavar="M",
        help="metres per range bin, for a bag without a RadarConfigurationMsg (default: the service reads the scan's "
        "width)",
    )
    bag.add_argument(
        "--bag-out",
        type=Path,
        metavar="OUT",
        help="write the answers as a ROS 2 bag OUT: /rafd/detections, /rafd/tracks, /rafd/odometry, /tf",
    )
    bag.add_argument(
        "--bag-storage", choices=("mcap", "sqlite3"), default="mcap", help="storage of --bag-out (default mcap)"
    )
    bag.add_argument(
        "--bag-scan", action="store_true", help="--bag-out also holds the scan (/rafd/scan, OccupancyGrid)"
    )
    bag.add_argument("--bag-flow", action="store_true", help="--bag-out also holds the flow (/rafd/flow, MarkerArray)")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds per request (default 30)")
    parser.add_argument(
        "--retries",
        type=int,
        default=4,
        metavar="N",
        help="post a frame again up to N times after 502/503/504, a lost connection or a timeout, with backoff "
        "(0.25 s doubling, at most 4 s; default 4; 0: never)",
    )
    parser.add_argument(
        "--api-key",
        default=os.environ.get("RAFD_API_KEY"),
        help="key for a service run with RAFD_API_KEYS (default: $RAFD_API_KEY; sent as X-API-Key)",
    )
    flags.add_quiet(parser)
    return parser


def repeat_hint(stream_id: str, chosen: bool) -> str:
    """What to do after a 409 on timestamps: the two ways out."""
    if chosen:
        return (
            f"stream {stream_id!r} already holds frames at or after these timestamps (an earlier run?): add --reset "
            f"to delete it first, or leave out --stream-id so that this run gets a new stream"
        )
    return f"stream {stream_id!r} refused the frame's timestamp: add --reset, or pass another --stream-id"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    flags.apply_quiet(args)
    try:
        sequence = read_sequence_or_bag(args)
        from rafd.viz.answer import AnswerView, decode_validity, draw_answer
        from rafd.viz.trails import Trails

        view = AnswerView(view_px=args.view, flow_step=args.flow_step, flow_scale=args.flow_scale)
        trails = Trails()
    except (OSError, ValueError) as exc:
        print(f"rafd-client: {exc}", file=sys.stderr)
        return 2
    frames = sequence.frames[: args.limit] if args.limit else sequence.frames
    if not frames:
        print(f"rafd-client: {args.sequence} holds no radar frames", file=sys.stderr)
        return 2
    if args.mcap is not None and not args.mcap.parent.is_dir():
        print(f"rafd-client: folder of --mcap {args.mcap} does not exist", file=sys.stderr)
        return 2
    if args.bag_out is not None and (args.bag_out.exists() or not args.bag_out.parent.is_dir()):
        problem = "exists (a new bag is written, never over one)" if args.bag_out.exists() else "has no folder"
        print(f"rafd-client: --bag-out {args.bag_out} {problem}", file=sys.stderr)
        return 2
    stream_id = args.stream_id or new_stream_id(sequence.name)
    out = args.out
    writer = answers = log = last_answer = bar = answer_bag = None
    completed = False
    boxes = retries = restarts = 0
    if out is not None:
        (out / "frames").mkdir(parents=True, exist_ok=True)
        answers = (out / "answers.jsonl").open("w")
    try:
        if args.mcap is not None:
            try:
                from rafd.viz.mcap import RadarMcapLog
            except ImportError as exc:
                raise ServiceError(f"--mcap needs the logs extra (pip install 'rafd[logs]'): {exc}") from exc
            log = RadarMcapLog(args.mcap)
        if args.bag_out is not None:
            from rafd.ros.writer import AnswerBag

            answer_bag = AnswerBag(args.bag_out, stream_id, args.bag_storage, args.bag_scan, args.bag_flow)
        if args.reset:
            existed = reset_stream(args.url, stream_id, args.timeout, args.api_key)
            print(f"stream {stream_id}: {'deleted on the service' if existed else 'not on the service'} (--reset)")
        print(f"posting {len(frames)} frames of {sequence.name} to stream {stream_id} at {args.url}")
        bar = progress.bar(desc=f"post {stream_id}", total=len(frames), unit="frame")
        boxes = 0
        previous: float | None = None  # the last frame answered: the chain the service must continue
        from_bag = bag_inputs(sequence, frames)
        drawn = out is not None or log is not None or (answer_bag is not None and args.bag_scan)
        for frame in frames:
            if from_bag is not None:  # a bag's scan: posted as the native (or polar) scan it is, drawn converted
                bag_input = next(from_bag)
                posted = bag_input.posted_png()
                frame = dataclasses.replace(frame, range_resolution_m=bag_input.scan.range_bin_m)
                scan = bag_input.cartesian() if drawn else np.zeros((0, 0), np.uint8)
                png = png_bytes(scan) if out is not None or log is not None else b""
            else:
                scan, png = frame.scan_and_png()
                posted = frame.posted_png(png)
            try:
                answer, used = post_with_retries(
                    max(0, args.retries),
                    functools.partial(
                        post_frame,
                        args.url,
                        stream_id,
                        frame,
                        posted,
                        not args.no_pose,
                        args.timeout,
                        args.api_key,
                        previous,
                    ),
                    f"frame {frame.number}",
                )
                retries += used
                last_answer, previous = answer, frame.timestamp
                if answer.get("stream_restarted") in ("gap", "previous_timestamp_mismatch"):
                    restarts += 1
            except ServiceError as exc:
                if exc.code == "timestamp_not_increasing":
                    raise ServiceError(
                        f"{exc}\n{repeat_hint(stream_id, args.stream_id is not None)}", exc.code
                    ) from exc
                raise
            boxes += len(answer["boxes"])
            bar.update()
            bar.set_postfix_str(
                f"{len(answer['boxes'])} boxes, {answer['frames_used']} frames used, "
                f"{answer['timing']['total_ms']:.0f} ms",
                refresh=False,
            )
            validity = None if not answer.get("flow") else decode_validity(answer["flow"])  # arrows only where valid
            if answer_bag is not None:
                answer_bag.write(
                    answer, frame.source.timestamp_ns, scan if args.bag_scan else None, sequence.resolution
                )
            if log is not None:
                log.write(logged_frame(frame, scan, png, answer, sequence.resolution, sequence.annotated, validity))
            if out is None or answers is None:  # (both or neither)
                continue
            answers.write(json.dumps(answer) + "\n")
            trails.add(answer)
            canvas = draw_answer(
                scan,
                answer,
                truth_polygons(frame, sequence.annotated),
                sequence.resolution,
                view,
                title=f"{sequence.name} frame {frame.number}",
                validity=validity,
                trails=trails.in_scan(answer, sequence.resolution),
            )
            if not cv2.imwrite(str(out / "frames" / f"{frame.number:06d}.png"), canvas):
                raise OSError(f"could not write {out / 'frames' / f'{frame.number:06d}.png'}")
            if writer is None:
                size = (canvas.shape[1], canvas.shape[0])
                writer = cv2.VideoWriter(
                    str(out / "sequence.mp4"), cv2.VideoWriter.fourcc(*"mp4v"), frame_rate(frames), size
                )
            writer.write(canvas)
        completed = True
    except (ServiceError, OSError, ValueError) as exc:
        print(f"rafd-client: {exc}", file=sys.stderr)
        return 1
    finally:
        if answer_bag is not None:  # complete or absent: kept only when every frame was answered and written
            if completed:
                answer_bag.close()
            else:
                answer_bag.abort()
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.release()
        if answers is not None:
            answers.close()
        if log is not None:
            if last_answer is not None:
                log.write_metadata(
                    "rafd-client",
                    {
                        "sequence": sequence.name,
                        "stream_id": stream_id,
                        "url": args.url,
                        "frames": log.frames,
                        "model_version": last_answer["model"]["version"],
                        "checkpoint_sha256": last_answer["model"]["checkpoint_sha256"],
                    },
                )
            log.close()
    print(f"stream {stream_id}: {len(frames)} frames answered, {boxes} boxes in all")
    if retries or restarts:
        print(f"stream {stream_id}: {retries} retries, {restarts} chains restarted by the service (failover)")
    if out is not None:
        print(f"wrote {len(frames)} frames, answers.jsonl and sequence.mp4 to {out}")
    if log is not None:
        print(f"wrote {log.frames} frames to the MCAP log {args.mcap}")
    if answer_bag is not None:
        print(f"wrote {answer_bag.scans} scans' detections, tracks and odometry to the ROS 2 bag {args.bag_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
