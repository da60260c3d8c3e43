"""The ROS 2 message types rafd reads and writes: rosbags' own ROS 2 Jazzy types (std_msgs, geometry_msgs,
sensor_msgs, nav_msgs, tf2_msgs, unique_identifier_msgs, visualization_msgs, builtin_interfaces) plus the definitions
shipped in rafd/ros/messages/ (navtech_msgs, radar_msgs, vision_msgs; their sources and licences: its README.md).
Nothing is fetched at run time.

A bag that carries its own definitions is read with them (they win over these: a driver's RadarConfigurationMsg of
another field layout reads as written); these fill in what a bag does not define (an older sqlite3 bag carries no
definitions at all).
"""

from __future__ import annotations

from functools import cache
from importlib import resources
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

B_SCAN = "navtech_msgs/msg/RadarBScanMsg"
CONFIGURATION = "navtech_msgs/msg/RadarConfigurationMsg"
# The older drivers' layout of CONFIGURATION (every field a big-endian byte array), registered under its own name so
# that both layouts live in one store: tried when a bag without definitions holds configuration messages that do not
# read in the typed layout.
LEGACY_CONFIGURATION = "rafd_navtech_legacy/msg/RadarConfigurationMsg"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
DETECTIONS = "vision_msgs/msg/Detection3DArray"
TRACKS = "radar_msgs/msg/RadarTracks"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
MARKERS = "visualization_msgs/msg/MarkerArray"

# Sequences longer than this are refused while a message is read (rosbags checks each one's length before reading
# it): the largest sequence rafd reads is a scan's pixels (a Navtech scan of 400 x 6848 bins is 2.7 million bytes).
MAX_SEQUENCE_LENGTH = 64 * 2**20


def _messages_folder() -> resources.abc.Traversable:
    return resources.files("rafd.ros") / "messages"


@cache
def shipped_definitions() -> dict[str, str]:
    """{type name: .msg text} of the definitions in rafd/ros/messages/ (LEGACY_CONFIGURATION under its own name)."""
    folder = _messages_folder()
    definitions: dict[str, str] = {}
    for package in ("navtech_msgs", "radar_msgs", "vision_msgs"):
        for entry in sorted((folder / package / "msg").iterdir(), key=lambda e: e.name):
            if entry.name.endswith(".msg"):
                definitions[f"{package}/msg/{entry.name[: -len('.msg')]}"] = entry.read_text()
    definitions[LEGACY_CONFIGURATION] = (folder / "navtech_msgs" / "legacy" / "RadarConfigurationMsg.msg").read_text()
    return definitions


@cache
def _shipped_fields() -> dict[str, tuple]:
    from rosbags.typesys import get_types_from_msg

    fields: dict[str, tuple] = {}
    for name, text in shipped_definitions().items():
        fields.update(get_types_from_msg(text, name))
    return fields


@cache
def _base_fields() -> dict[str, tuple]:
    from rosbags.typesys import Stores, get_typestore

    return dict(get_typestore(Stores.ROS2_JAZZY).fielddefs)


def typestore(own: dict[str, tuple] | None = None) -> Typestore:
    """A fresh store of rosbags' ROS 2 Jazzy types and the shipped ones, `own` (a bag's definitions, as
    rosbags.typesys.get_types_from_msg gives them) registered first so that they win; sequences bounded by
    MAX_SEQUENCE_LENGTH."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.max_sequence_length = MAX_SEQUENCE_LENGTH
    own = own or {}
    store.register(own)
    store.register({name: value for name, value in {**_base_fields(), **_shipped_fields()}.items() if name not in own})
    return store
