"""Tracks over time, torch-free (numpy + scipy): every detected box a track with its ground velocity.

One implementation for `rafd eval` and the service. A stream's tracks are one immutable TrackerState; step() takes
it with one scan's detections, world pose, time and (optionally) the newest pair's flow, and returns the scan's
TrackedBoxes and the next state, leaving the state passed in valid and unchanged:

    state = TrackerState.empty()
    tracked, state = step(state, boxes, pose, timestamp, scores=scores, flow=FlowField(grid, flow, interval_s))

docs/tracking.md says what is measured, how, and which settings were chosen.
"""

from rafd.tracking.flow import FlowField, FlowGrid, flow_velocity, sample_box, sample_centre
from rafd.tracking.inputs import FrameRefused
from rafd.tracking.settings import MATCHING, VELOCITY_MODES, TrackerSettings
from rafd.tracking.state import STATUS_NAMES, VELOCITY_SOURCES, TrackerState
from rafd.tracking.tracker import DEFAULT_SETTINGS, TrackedBoxes, step

__all__ = [
    "DEFAULT_SETTINGS",
    "MATCHING",
    "STATUS_NAMES",
    "VELOCITY_MODES",
    "VELOCITY_SOURCES",
    "FlowField",
    "FlowGrid",
    "FrameRefused",
    "TrackedBoxes",
    "TrackerSettings",
    "TrackerState",
    "flow_velocity",
    "sample_box",
    "sample_centre",
    "step",
]
