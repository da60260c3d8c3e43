"""RaFD network in PyTorch (paper section 2): build_model(cfg) -> RaFD.

backbone.py + neck.py + enhance.py -> per-frame features S; flow.py -> pair flow V;
propagation.py -> flow-guided deformable propagation chain; head.py + decoder.py -> boxes.
"""

from rafd.model.align import relative_pose_torch
from rafd.model.build import build_model, count_parameters
from rafd.model.detector import RaFD

__all__ = ["RaFD", "build_model", "count_parameters", "relative_pose_torch"]
