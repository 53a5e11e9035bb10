"""Depth network: ResNet-18 encoder + decoder with skip connections, sigmoid disparities at 4 scales.

Convention:
    Input (B,3,H,W) RGB in [0,1], H and W multiples of 32. Output dict ``{s: (B,1,H/2^s,W/2^s)}`` for
    s = 0..3, sigmoid "disparities" in (0,1) that :func:`disp_to_depth` maps to depth in
    [min_depth, max_depth]. A stereo-trained model (``model=depth_stereo``, trained with the true baseline
    of the calibration) outputs metres; a monocular one is up to an unknown scale.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK_SHAPE
from torch import nn

from dfvo.models.resnet import ResNet18Encoder

DECODER_CHANNELS = (16, 32, 64, 128, 256)
SCALES = (0, 1, 2, 3)


def disp_to_depth(disp: torch.Tensor, min_depth: float = 0.1, max_depth: float = 100.0) -> torch.Tensor:
    """Map a sigmoid output in [0,1] to depth: ``1 / (1/max + (1/min - 1/max) * disp)``.

    Args:
        disp: (B,1,H,W) sigmoid disparity.
        min_depth, max_depth: depth at ``disp = 1`` and ``disp = 0``.

    Returns:
        (B,1,H,W) depth in [min_depth, max_depth] (metres for a stereo-trained model).
    """
    if not 0 < min_depth < max_depth:
        raise ValueError(f"disp_to_depth: expected 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    min_disp, max_disp = 1.0 / max_depth, 1.0 / min_depth
    return 1.0 / (min_disp + (max_disp - min_disp) * disp)


class ConvBlock(nn.Module):
    """3x3 convolution with reflection padding followed by ELU."""

    def __init__(self, in_ch: int, out_ch: int, activation: bool = True) -> None:
        super().__init__()
        self.pad = nn.ReflectionPad2d(1)
        self.conv = nn.Conv2d(in_ch, out_ch, 3)
        self.act = nn.ELU(inplace=True) if activation else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv(self.pad(x)))


class DepthDecoder(nn.Module):
    """U-Net style decoder over the 5 ResNet feature maps; disparity heads at scales 0..3."""

    def __init__(self, num_ch_enc: tuple[int, ...]) -> None:
        super().__init__()
        self.up0 = nn.ModuleList()
        self.up1 = nn.ModuleList()
        for i in range(5):
            in_ch = num_ch_enc[-1] if i == 4 else DECODER_CHANNELS[i + 1]
            self.up0.append(ConvBlock(in_ch, DECODER_CHANNELS[i]))
            skip = num_ch_enc[i - 1] if i > 0 else 0
            self.up1.append(ConvBlock(DECODER_CHANNELS[i] + skip, DECODER_CHANNELS[i]))
        self.heads = nn.ModuleList([ConvBlock(DECODER_CHANNELS[s], 1, activation=False) for s in SCALES])

    def forward(self, features: list[torch.Tensor]) -> dict[int, torch.Tensor]:
        out: dict[int, torch.Tensor] = {}
        x = features[-1]
        for i in range(4, -1, -1):
            x = F.interpolate(self.up0[i](x), scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat([x, features[i - 1]], dim=1)
            x = self.up1[i](x)
            if i in SCALES:
                out[i] = torch.sigmoid(self.heads[i](x))
        return out


class DepthNet(nn.Module):
    """Monocular depth network (monodepth2-style architecture).

    Args:
        min_depth, max_depth: depth range of :meth:`depth`.
        init_depth: if given, the disparity heads start (bias) at the disparity of this depth, so that an
            untrained stereo model predicts a plausible metric depth: with the sigmoid at 0.5 the initial
            depth would be ~0.2 m, whose stereo disparity (fx * b / z, ~500 px at 320 px width) leaves the
            image and gives the stereo term no gradient.

    Shape:
        - Input: (B,3,H,W), H, W multiples of 32.
        - Output of ``forward``: dict scale -> (B,1,H/2^s,W/2^s) disparity in (0,1), scales 0..3.
    """

    def __init__(self, min_depth: float = 0.1, max_depth: float = 100.0, init_depth: float | None = None) -> None:
        super().__init__()
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.encoder = ResNet18Encoder(1)
        self.decoder = DepthDecoder(self.encoder.num_ch_enc)
        if init_depth is not None:
            if not self.min_depth < init_depth < self.max_depth:
                raise ValueError(f"DepthNet: init_depth {init_depth} outside ({min_depth}, {max_depth})")
            disp = (1.0 / init_depth - 1.0 / self.max_depth) / (1.0 / self.min_depth - 1.0 / self.max_depth)
            with torch.no_grad():
                for head in self.decoder.heads:
                    head.conv.bias.fill_(math.log(disp / (1.0 - disp)))

    def forward(self, image: torch.Tensor) -> dict[int, torch.Tensor]:
        KORNIA_CHECK_SHAPE(image, ["B", "3", "H", "W"])
        return self.decoder(self.encoder(image))

    @torch.no_grad()
    def depth(self, image: torch.Tensor) -> torch.Tensor:
        """Full-resolution depth (B,1,H,W) of ``image`` (B,3,H,W) in [min_depth, max_depth]."""
        return disp_to_depth(self.forward(image)[0], self.min_depth, self.max_depth)
