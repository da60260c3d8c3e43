"""The exported graphs' interface: input/output names per form and the metadata every RaFD export carries."""
from __future__ import annotations

METADATA_KEYS = ("config", "input_size", "resolution", "num_frames", "class_names", "checkpoint_sha256", "version",
                 "form", "feature_channels")
FORMS = ("step", "window")


def graph_inputs(form: str, num_frames: int) -> tuple[str, ...]:
    """Input names of an exported graph, in order."""
    if form == "window":
        return ("frames", "poses")
    return ("frame", "poses", "past_features", "past_flows")[: min(num_frames + 1, 4)]


def graph_outputs(form: str, num_frames: int) -> tuple[str, ...]:
    """Output names of an exported graph, in order."""
    if num_frames == 1:
        return ("heatmap", "scores", "boxes")
    return ("heatmap", "scores", "boxes", "flow") + (("features",) if form == "step" else ())
