"""Gain-robust input normalisation: the network's first module, so PyTorch and the exported graph compute it alike.

A radar scan's absolute grey level depends on the receiver's gain, the weather and the range; a detector trained on
one simulator's brightness reads it literally. `LocalContrast` gives the network log-compressed grey levels
standardised by the mean and spread of the window around each pixel:

    l = log(1 + 255 x) / log(256)               (x = grey / 255, the rafd.preprocess frame)
    out = (l - mean_w(l)) / sqrt(var_w(l) + eps)  (w: a window x window box around the pixel, inside the image)

A gain change g adds log(g) / log(256) to l and cancels in l - mean; a gamma change multiplies log grey and cancels
in the division; the noise floor's rise with range is removed locally. The window statistics are separable box
means (two 1-D average pools, count_include_pad=False), which ONNX exports as AveragePool. "none" keeps the paper's
input x = grey / 255.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

NORMALISATIONS = ("none", "local_contrast")


def box_mean(x: Tensor, window: int) -> Tensor:
    """[B, C, H, W] -> mean over the window x window box around each pixel, inside the image."""
    half = window // 2
    x = F.avg_pool2d(x, (window, 1), stride=1, padding=(half, 0), count_include_pad=False)  # along rows
    return F.avg_pool2d(x, (1, window), stride=1, padding=(0, half), count_include_pad=False)  # along columns


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
            log_grey = torch.log1p(frames.float() * 255.0) * (1.0 / math.log(256.0))
            mean = box_mean(log_grey, self.window)
            variance = (box_mean(log_grey * log_grey, self.window) - mean * mean).clamp_min(0.0)
            return (log_grey - mean) * torch.rsqrt(variance + self.eps)


def build_normalisation(kind: str, window: int) -> nn.Module:
    if kind not in NORMALISATIONS:
        raise ValueError(f"input normalisation must be one of {NORMALISATIONS}, got {kind!r}")
    return nn.Identity() if kind == "none" else LocalContrast(window)
