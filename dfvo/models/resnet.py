"""ResNet-18 encoder in plain PyTorch (no torchvision), for the depth (3 channels) and pose (6 channels) nets.

Convention:
    Input (B,C,H,W) images in [0,1] with C = 3 * num_frames; the encoder normalises them with the
    ImageNet mean/std (as monodepth2 does, by ``(x - 0.45) / 0.225``). Output: 5 feature maps at strides
    2, 4, 8, 16, 32 with 64, 64, 128, 256, 512 channels.
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE
from torch import nn

ENCODER_CHANNELS = (64, 64, 128, 256, 512)


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

    Shape:
        - Input: (B, 3*num_input_frames, H, W), H and W multiples of 32.
        - Output: list of 5 tensors (B,64,H/2,W/2), (B,64,H/4,W/4), (B,128,H/8,W/8), (B,256,H/16,W/16),
          (B,512,H/32,W/32).
    """

    def __init__(self, num_input_frames: int = 1) -> None:
        super().__init__()
        if num_input_frames < 1:
            raise ValueError(f"ResNet18Encoder: num_input_frames must be >= 1, got {num_input_frames}")
        self.in_channels = 3 * num_input_frames
        self.num_ch_enc = ENCODER_CHANNELS
        self.conv1 = nn.Conv2d(self.in_channels, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.layer1 = nn.Sequential(BasicBlock(64, 64), BasicBlock(64, 64))
        self.layer2 = nn.Sequential(BasicBlock(64, 128, 2), BasicBlock(128, 128))
        self.layer3 = nn.Sequential(BasicBlock(128, 256, 2), BasicBlock(256, 256))
        self.layer4 = nn.Sequential(BasicBlock(256, 512, 2), BasicBlock(512, 512))
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
