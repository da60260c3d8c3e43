"""Basic-block ResNet on one radar channel (ResNet-34 = blocks (3, 4, 6, 3) in the paper config)."""

from __future__ import annotations

from typing import cast

from torch import Tensor, nn


def conv_bn(in_channels: int, out_channels: int, kernel: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel, stride=stride, padding=kernel // 2, bias=False),
        nn.BatchNorm2d(out_channels),
    )


class BasicBlock(nn.Module):
    """Two 3x3 convs with an identity (or 1x1 projection) shortcut: [B, Cin, H, W] -> [B, Cout, H/s, W/s]."""

    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = conv_bn(in_channels, out_channels, 3, stride)
        self.conv2 = conv_bn(out_channels, out_channels, 3)
        self.relu = nn.ReLU(inplace=True)
        needs_projection = stride != 1 or in_channels != out_channels
        self.shortcut = conv_bn(in_channels, out_channels, 1, stride) if needs_projection else nn.Identity()
        # Zero-init the last BN scale: each residual block starts as identity (Goyal et al.), stabler at lr 2e-4.
        nn.init.zeros_(cast(nn.BatchNorm2d, self.conv2[1]).weight)  # conv_bn: (Conv2d, BatchNorm2d)

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.conv1(x))
        return self.relu(self.conv2(out) + self.shortcut(x))


class ResNet(nn.Module):
    """[B, 1, S, S] -> list of stage maps at strides 4, 8, 16, (32) with `channels` each."""

    def __init__(self, blocks: tuple[int, ...], channels: tuple[int, ...], in_channels: int = 1) -> None:
        super().__init__()
        # The stem always reaches stride 4 (conv stride 2 + max-pool stride 2) so stage 1 is at stride 4,
        # the output stride of the BEV map (TempoRadar: 256 -> 64).
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, channels[0], 7, stride=2, padding=3, bias=False),
            nn.BatchNorm2d(channels[0]),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, stride=2, padding=1),
        )
        stages = []
        previous = channels[0]
        for index, (count, width) in enumerate(zip(blocks, channels)):
            stride = 1 if index == 0 else 2
            layers = [BasicBlock(previous, width, stride)] + [BasicBlock(width, width, 1) for _ in range(count - 1)]
            stages.append(nn.Sequential(*layers))
            previous = width
        self.stages = nn.ModuleList(stages)
        self.out_channels = tuple(channels)
        self.strides = tuple(4 * 2**index for index in range(len(channels)))
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: Tensor) -> list[Tensor]:
        x = self.stem(x)  # [B, C0, S/4, S/4]
        outputs = []
        for stage in self.stages:
            x = stage(x)
            outputs.append(x)
        return outputs
