"""Gain-robust input normalisation: the network's first module, so PyTorch and the exported graph compute it alike.

A radar scan's absolute grey level depends on the receiver's gain, the weather and the range; a detector trained on
one simulator's brightness reads it literally. `LocalContrast` gives the network log-compressed grey levels
standardised by the mean and spread of the window around each pixel:

    l = log(1 + 255 x) / log(256)               (x = grey / 255, the rafd.preprocess frame)
    out = (l - mean_w(l)) / sqrt(var_w(l) + eps)  (w: a window x window box around the pixel, inside the image)

A gain change g adds log(g) / log(256) to l and cancels in l - mean; a gamma change multiplies log grey and cancels
in the division; the noise floor's rise with range is removed locally. The window statistics are box means over
the pixels inside the image, taken on a grid STATS_STRIDE times coarser (4 x 4 pixel means, a window of window // 4
coarse cells, one ONNX AveragePool excluding the padding) and upsampled bilinearly: the statistics of a 47-pixel
window are smooth, and a full-resolution 47-pixel average pool was a tenth of a training step.
"none" keeps the paper's input x = grey / 255.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

NORMALISATIONS = ("none", "local_contrast")
STATS_STRIDE = 4  # pixels per side of the coarse cells the window statistics are computed on


def box_mean(x: Tensor, window: int) -> Tensor:
    """[B, C, H, W] -> mean over the window x window box around each pixel, inside the image (odd window)."""
    return F.avg_pool2d(x, window, stride=1, padding=window // 2, count_include_pad=False)


class LocalContrast(nn.Module):
    """[B, 1, S, S] frames in [0, 1] -> [B, 1, S, S] log grey standardised over a local window."""

    def __init__(self, window: int, eps: float = 1e-4) -> None:
        super().__init__()
        if window < 3 or window % 2 == 0:
            raise ValueError(f"the normalisation window must be an odd number of pixels >= 3, got {window}")
        self.window = window
        self.eps = eps

    def forward(self, frames: Tensor) -> Tensor:
        with torch.autocast(frames.device.type, enabled=False):  # statistics in float32 whatever the autocast
            log_grey = torch.log1p(frames.float() * 255.0) * (1.0 / math.log(256.0))  # [B, 1, S, S]
            size = log_grey.shape[-2:]
            # Centred on the frame's mean first: var_w(l) = E_w[d^2] - E_w[d]^2 for d = l - c and any constant c,
            # and with c near the local means both terms stay small. A runtime that computes this graph in bf16
            # (OpenVINO's bf16 hint converts every op) then loses ~0.03 of a unit output, not the whole signal
            # (uncentred running sums lost up to 56).
            centred = log_grey - log_grey.mean(dim=(2, 3), keepdim=True)  # [B, 1, S, S]
            coarse = F.avg_pool2d(torch.cat([centred, centred * centred], 1), STATS_STRIDE)  # [B, 2, S/4, S/4]
            cells = max(1, (self.window // STATS_STRIDE) | 1)  # odd window in coarse cells
            moments = F.interpolate(box_mean(coarse, cells), size=size, mode="bilinear", align_corners=False)
            mean, mean_square = moments[:, :1], moments[:, 1:]  # [B, 1, S, S] each
            variance = (mean_square - mean * mean).clamp_min(0.0)
            return (centred - mean) * torch.rsqrt(variance + self.eps)


def build_normalisation(kind: str, window: int) -> nn.Module:
    if kind not in NORMALISATIONS:
        raise ValueError(f"input normalisation must be one of {NORMALISATIONS}, got {kind!r}")
    return nn.Identity() if kind == "none" else LocalContrast(window)
