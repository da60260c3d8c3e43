"""The exported graphs' interface: input/output names per form and the metadata every RaFD export carries.

Step graphs cache the previous frame's flow features E = phi(S) (input past_flow_features, output
flow_features) beside its enhanced features; step graphs exported before that cache existed (no such input)
are still served: the runner reads which contract a graph follows from its inputs (`flow_cache`).
"""

from __future__ import annotations

METADATA_KEYS = (
    "config",
    "input_size",
    "resolution",
    "num_frames",
    "class_names",
    "checkpoint_sha256",
    "version",
    "form",
    "feature_channels",
)
FORMS = ("step", "window")


def graph_inputs(form: str, num_frames: int, flow_cache: bool = True) -> tuple[str, ...]:
    """Input names of an exported graph, in order."""
    if form == "window":
        return ("frames", "poses")
    names = ("frame", "poses", "past_features", "past_flows")[: min(num_frames + 1, 4)]
    return names + (("past_flow_features",) if flow_cache and num_frames > 1 else ())


def graph_outputs(form: str, num_frames: int, flow_cache: bool = True) -> tuple[str, ...]:
    """Output names of an exported graph, in order."""
    if num_frames == 1:
        return ("heatmap", "scores", "boxes")
    if form == "window":
        return ("heatmap", "scores", "boxes", "flow")
    return ("heatmap", "scores", "boxes", "flow", "features") + (("flow_features",) if flow_cache else ())
