"""One /detect answer -> the ROS 2 messages rafd writes, in REP-103 axes (rafd.ros.axes) and REP-105 frames:

- vision_msgs/Detection3DArray: per box its centre pose and yaw, size (x = length, y = width, z = 0: a scanning radar
  measures no height), one hypothesis (class name, score), and `id` (rafd.ros.tracks: the track id, else a per-box
  name);
- radar_msgs/RadarTracks: per box its UUID, position, velocity and size with their covariances (NaN where the
  answer does not say: every covariance without tracking, acceleration always), classification 32000 + class id
  (radar_msgs reserves 32000 and up for a vendor's classes; the shipped model's class 0 is "vehicle");
- nav_msgs/Odometry and tf2_msgs/TFMessage: the pose the service used (the request's or odometry's) of the radar in
  the stream's world frame, named `odom` (REP-105: continuous, drifting); twist not estimated (zero, covariance
  unknown);
- on request, nav_msgs/OccupancyGrid of the scan (grey 0-255 as 0-100) and visualization_msgs/MarkerArray of the flow
  (one arrow per valid cell, metres per frame pair), both in the radar's frame: RViz and Foxglove draw both in 3D.
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np

from rafd.ros import types
from rafd.ros.axes import box_to_ros, pose_to_ros, position_to_ros, yaw_quaternion
from rafd.ros.build import make
from rafd.ros.tracks import NAN, track_fields, upper_triangle_3d

FRAME_RADAR = "radar"
FRAME_ODOM = "odom"
VENDOR_CLASS_BASE = 32000  # radar_msgs: "additional vendor-specific classifications are permitted starting from 32000"
UNKNOWN_COVARIANCE = [NAN] * 6


def header(store: Any, stamp_ns: int, frame_id: str) -> Any:
    seconds, nanoseconds = divmod(int(stamp_ns), 1_000_000_000)
    stamp = make(store, "builtin_interfaces/msg/Time", sec=seconds, nanosec=nanoseconds)
    return make(store, "std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)


def _pose(store: Any, x: float, y: float, yaw: float) -> Any:
    qx, qy, qz, qw = yaw_quaternion(yaw)
    return make(
        store,
        "geometry_msgs/msg/Pose",
        position=make(store, "geometry_msgs/msg/Point", x=x, y=y, z=0.0),
        orientation=make(store, "geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
    )


def _vector(store: Any, x: float, y: float, z: float) -> Any:
    return make(store, "geometry_msgs/msg/Vector3", x=float(x), y=float(y), z=float(z))


def _ros_box(box: dict[str, Any]) -> Any:
    return box_to_ros(box["x"], box["y"], box["width"], box["length"], box["yaw"])


def detections(store: Any, answer: dict[str, Any], stamp_ns: int, stream_id: str, frame_id: str = FRAME_RADAR) -> Any:
    """vision_msgs/Detection3DArray of the answer's boxes."""
    stamped = header(store, stamp_ns, frame_id)
    found = []
    for index, box in enumerate(answer["boxes"]):
        ros = _ros_box(box)
        centre = _pose(store, ros.x, ros.y, ros.yaw)
        hypothesis = make(
            store,
            "vision_msgs/msg/ObjectHypothesisWithPose",
            hypothesis=make(store, "vision_msgs/msg/ObjectHypothesis", class_id=str(box["class"]), score=box["score"]),
            pose=make(store, "geometry_msgs/msg/PoseWithCovariance", pose=centre),
        )
        bbox = make(
            store, "vision_msgs/msg/BoundingBox3D", center=centre, size=_vector(store, ros.size_x, ros.size_y, 0)
        )
        fields = track_fields(box, stream_id, stamp_ns, index)
        found.append(
            make(store, "vision_msgs/msg/Detection3D", header=stamped, results=[hypothesis], bbox=bbox, id=fields.id)
        )
    return make(store, types.DETECTIONS, header=stamped, detections=found)


def tracks(store: Any, answer: dict[str, Any], stamp_ns: int, stream_id: str, frame_id: str = FRAME_RADAR) -> Any:
    """radar_msgs/RadarTracks of the answer's boxes (rafd.ros.tracks for ids, velocity and covariances)."""
    listed = []
    for index, box in enumerate(answer["boxes"]):
        ros = _ros_box(box)
        fields = track_fields(box, stream_id, stamp_ns, index)
        listed.append(
            make(
                store,
                "radar_msgs/msg/RadarTrack",
                uuid=make(store, "unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(fields.uuid, np.uint8).copy()),
                position=make(store, "geometry_msgs/msg/Point", x=ros.x, y=ros.y, z=0.0),
                velocity=_vector(store, fields.velocity[0], fields.velocity[1], NAN),
                acceleration=_vector(store, NAN, NAN, NAN),
                size=_vector(store, ros.size_x, ros.size_y, NAN),
                classification=VENDOR_CLASS_BASE + int(box.get("class_id", 0)),
                position_covariance=np.array(UNKNOWN_COVARIANCE, np.float32),
                velocity_covariance=np.array(upper_triangle_3d(fields.velocity_covariance), np.float32),
                acceleration_covariance=np.array(UNKNOWN_COVARIANCE, np.float32),
                size_covariance=np.array(UNKNOWN_COVARIANCE, np.float32),
            )
        )
    return make(store, types.TRACKS, header=header(store, stamp_ns, frame_id), tracks=listed)


def _world_pose(answer: dict[str, Any]) -> tuple[float, float, float]:
    pose = answer["pose"]
    return pose_to_ros(pose["x"], pose["y"], pose["yaw"])


def odometry(store: Any, answer: dict[str, Any], stamp_ns: int, child_frame: str = FRAME_RADAR) -> Any:
    """nav_msgs/Odometry: the radar's pose in `odom` (the stream's world frame in REP-103 axes)."""
    x, y, yaw = _world_pose(answer)
    unknown = np.zeros(36, np.float64)
    unknown[0] = -1.0  # the covariance is not known (the convention of sensor_msgs' -1 in the first element)
    return make(
        store,
        types.ODOMETRY,
        header=header(store, stamp_ns, FRAME_ODOM),
        child_frame_id=child_frame,
        pose=make(store, "geometry_msgs/msg/PoseWithCovariance", pose=_pose(store, x, y, yaw), covariance=unknown),
        twist=make(store, "geometry_msgs/msg/TwistWithCovariance", covariance=unknown.copy()),
    )


def transform(store: Any, answer: dict[str, Any], stamp_ns: int, child_frame: str = FRAME_RADAR) -> Any:
    """tf2_msgs/TFMessage odom -> radar (what viewers need to place the radar frame in odom)."""
    x, y, yaw = _world_pose(answer)
    qx, qy, qz, qw = yaw_quaternion(yaw)
    moved = make(
        store,
        "geometry_msgs/msg/Transform",
        translation=_vector(store, x, y, 0.0),
        rotation=make(store, "geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
    )
    stamped = make(
        store,
        "geometry_msgs/msg/TransformStamped",
        header=header(store, stamp_ns, FRAME_ODOM),
        child_frame_id=child_frame,
        transform=moved,
    )
    return make(store, types.TF, transforms=[stamped])


def scan_grid(store: Any, scan: np.ndarray, resolution: float, stamp_ns: int, frame_id: str = FRAME_RADAR) -> Any:
    """nav_msgs/OccupancyGrid of a Cartesian scan (uint8 [N, N], radar at the centre, x right, y forward = image up)
    in the radar's frame: cell (i, j) lies i cells along ROS x (forward) and j along ROS y (left) from the origin, so
    the grid is the image turned (image[::-1, ::-1].T); grey 0-255 -> 0-100."""
    size = int(scan.shape[0])
    grid = np.ascontiguousarray(np.asarray(scan)[::-1, ::-1].T)
    values = np.round(grid.astype(np.float32) * (100.0 / 255.0)).astype(np.int8).reshape(-1)
    half = size / 2.0 * resolution
    info = make(
        store,
        "nav_msgs/msg/MapMetaData",
        map_load_time=header(store, stamp_ns, frame_id).stamp,
        resolution=float(resolution),
        width=size,
        height=size,
        origin=_pose(store, -half, -half, 0.0),
    )
    return make(store, types.OCCUPANCY_GRID, header=header(store, stamp_ns, frame_id), info=info, data=values)


MIN_FLOW_M = 0.05  # cells moving less get no segment (the pictures' threshold, rafd.viz)


def _decoded(flow: dict[str, Any], field: Any, shape: tuple[int, ...]) -> np.ndarray:
    """An answer's flow array in its `encoding` (docs/api.md: nested lists, or base64 of little-endian float16)."""
    if flow["encoding"] == "base64-float16":
        return np.frombuffer(base64.b64decode(field), dtype="<f2").reshape(shape).astype(np.float64)
    return np.asarray(field, dtype=np.float64).reshape(shape)


def flow_markers(store: Any, answer: dict[str, Any], stamp_ns: int, frame_id: str = FRAME_RADAR) -> Any:
    """visualization_msgs/MarkerArray: one LINE_LIST of the flow's valid cells (each a segment from the cell centre
    along its motion over the frame pair, metres), replacing the last one (DELETEALL first)."""
    stamped = header(store, stamp_ns, frame_id)
    clear = make(store, "visualization_msgs/msg/Marker", header=stamped, ns="rafd_flow", action=3)  # DELETEALL
    flow = answer.get("flow")
    if not flow:
        return make(store, types.MARKERS, markers=[clear])
    grid = flow["grid"]
    values = _decoded(flow, flow["values"], tuple(int(n) for n in flow["shape"]))  # [2, Hf, Wf] metres
    rows, cols = np.meshgrid(np.arange(grid["height"]), np.arange(grid["width"]), indexing="ij")
    keep = np.hypot(values[0], values[1]) > MIN_FLOW_M
    if flow.get("validity") is not None:
        validity = _decoded(flow, flow["validity"], (int(grid["height"]), int(grid["width"])))
        keep &= validity >= float(flow["validity_min"])
    resolution = float(grid["cell_size_m"]) / float(grid["stride_px"])
    half = answer["input"]["posted_size"] / 2.0
    points = []
    for row, col in zip(rows[keep], cols[keep]):
        u = grid["origin_px"][0] + (col + 0.5) * grid["stride_px"]  # the cell centre, posted pixels
        v = grid["origin_px"][1] + (row + 0.5) * grid["stride_px"]
        dx, dy = float(values[0, row, col]), float(values[1, row, col])
        x, y = (u - half) * resolution, (half - v) * resolution  # service axes, metres
        for px, py in ((x, y), (x + dx, y + dy)):
            rx, ry = position_to_ros(px, py)
            points.append(make(store, "geometry_msgs/msg/Point", x=rx, y=ry, z=0.0))
    lines = make(
        store,
        "visualization_msgs/msg/Marker",
        header=stamped,
        ns="rafd_flow",
        id=0,
        type=5,  # LINE_LIST
        action=0,
        pose=_pose(store, 0.0, 0.0, 0.0),
        scale=_vector(store, 0.15, 0.0, 0.0),
        color=make(store, "std_msgs/msg/ColorRGBA", r=0.1, g=0.8, b=1.0, a=1.0),
        points=points,
    )
    return make(store, types.MARKERS, markers=[clear, lines])
