"""ResNet-18 encoder in plain PyTorch (no torchvision), for the depth (3 channels) and pose (6 channels) nets.

Convention:
    Input (B,C,H,W) images in [0,1] with C = 3 * num_frames; the encoder normalises them with the
    ImageNet mean/std (as monodepth2 does, by ``(x - 0.45) / 0.225``). Output: 5 feature maps at strides
    2, 4, 8, 16, 32 with 64, 64, 128, 256, 512 channels (times ``width``: a narrower network, e.g. 0.5 for a
    quarter of the multiply-adds).
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE
from torch import nn

ENCODER_CHANNELS = (64, 64, 128, 256, 512)


def scaled_channels(channels: tuple[int, ...], width: float) -> tuple[int, ...]:
    """``channels`` times ``width`` (> 0), rounded to multiples of 8 (at least 8): the layer widths of a narrower
    (or wider) network; ``width=1`` returns ``channels``."""
    if not width > 0:
        raise ValueError(f"network width {width}; expected a positive channel multiplier (1: the full network)")
    return tuple(max(8, int(round(c * width / 8)) * 8) for c in channels)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with batch norm and an identity (or 1x1 projected) shortcut."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(nn.Conv2d(in_ch, out_ch, 1, stride, bias=False), nn.BatchNorm2d(out_ch))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18Encoder(nn.Module):
    """ResNet-18 feature extractor.

    Args:
        num_input_frames: 1 for the depth network (3 channels), 2 for the pose network (6 channels).
        width: channel multiplier (:func:`scaled_channels`); 1 is ResNet-18.

    Shape:
        - Input: (B, 3*num_input_frames, H, W), H and W multiples of 32.
        - Output: list of 5 tensors (B,C0,H/2,W/2), (B,C1,H/4,W/4), (B,C2,H/8,W/8), (B,C3,H/16,W/16),
          (B,C4,H/32,W/32), ``num_ch_enc`` = (C0..C4) = (64, 64, 128, 256, 512) at ``width=1``.
    """

    def __init__(self, num_input_frames: int = 1, width: float = 1.0) -> None:
        super().__init__()
        if num_input_frames < 1:
            raise ValueError(f"ResNet18Encoder: num_input_frames must be >= 1, got {num_input_frames}")
        self.in_channels = 3 * num_input_frames
        self.num_ch_enc = c = scaled_channels(ENCODER_CHANNELS, width)
        self.conv1 = nn.Conv2d(self.in_channels, c[0], 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(c[0])
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(c[0], c[1]), BasicBlock(c[1], c[1]))
        self.layer2 = nn.Sequential(BasicBlock(c[1], c[2], 2), BasicBlock(c[2], c[2]))
        self.layer3 = nn.Sequential(BasicBlock(c[2], c[3], 2), BasicBlock(c[3], c[3]))
        self.layer4 = nn.Sequential(BasicBlock(c[3], c[4], 2), BasicBlock(c[4], c[4]))
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        # zero-init the last BN of each block: every residual block starts as the identity (stable from scratch)
        for m in self.modules():
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        KORNIA_CHECK_SHAPE(x, ["B", str(self.in_channels), "H", "W"])
        if x.shape[-2] % 32 or x.shape[-1] % 32:
            raise ValueError(f"ResNet18Encoder: height and width must be multiples of 32, got {tuple(x.shape[-2:])}")
        x = (x - 0.45) / 0.225
        f0 = self.relu(self.bn1(self.conv1(x)))
        f1 = self.layer1(self.maxpool(f0))
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [f0, f1, f2, f3, f4]
