"""Pose network: 6-channel ResNet-18 encoder + pose decoder giving a relative 6-DoF pose.

Convention:
    ``PoseNet(image_a, image_b)`` predicts ``T_b_a`` (4,4): it maps points of camera a into camera b
    (``dfvo.geometry.se3`` convention), parameterised as an axis-angle vector (radians) and a
    translation. The decoder output is multiplied by 0.01 so that the initial prediction is a small
    motion (monodepth2's scaling of the pose output).
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE
from kornia.geometry.conversions import rotation_matrix_to_axis_angle
from torch import nn

from dfvo.geometry.se3 import pose_from_axis_angle
from dfvo.models.resnet import ResNet18Encoder

POSE_OUTPUT_SCALE = 0.01


class PoseDecoder(nn.Module):
    """1x1 squeeze, two 3x3 convolutions and a 1x1 head to 6 numbers, averaged over the image."""

    def __init__(self, in_ch: int = 512) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(in_ch, 256, 1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, 3, 1, 1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, 3, 1, 1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 6, 1),
        )

    def forward(self, feature: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.net[:-1](feature)
        with torch.autocast(x.device.type, enabled=False):  # the pose in float32 under autocast (bf16 training)
            out = POSE_OUTPUT_SCALE * self.net[-1](x.float()).mean(dim=(2, 3))
        return out[:, :3], out[:, 3:]


class PoseNet(nn.Module):
    """Relative camera pose from two images.

    Shape:
        - Input: image_a, image_b (B,3,H,W), H, W multiples of 32.
        - Output of ``forward``: ``T_b_a`` (B,4,4). :meth:`parameters_of` gives (axis_angle (B,3), t (B,3)).
    """

    def __init__(self) -> None:
        super().__init__()
        self.encoder = ResNet18Encoder(2)
        self.decoder = PoseDecoder(self.encoder.num_ch_enc[-1])

    def parameters_of(self, image_a: torch.Tensor, image_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        KORNIA_CHECK_SHAPE(image_a, ["B", "3", "H", "W"])
        KORNIA_CHECK_SHAPE(image_b, ["B", "3", "H", "W"])
        return self.decoder(self.encoder(torch.cat([image_a, image_b], dim=1))[-1])

    def forward(self, image_a: torch.Tensor, image_b: torch.Tensor) -> torch.Tensor:
        axis_angle, translation = self.parameters_of(image_a, image_b)
        with torch.autocast(axis_angle.device.type, enabled=False):
            return pose_from_axis_angle(axis_angle, translation)


def pose_to_axis_angle(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`dfvo.geometry.se3.pose_from_axis_angle`: (B,4,4) -> axis-angle (B,3), translation (B,3)."""
    KORNIA_CHECK_SHAPE(T, ["B", "4", "4"])
    return rotation_matrix_to_axis_angle(T[:, :3, :3].contiguous()), T[:, :3, 3]
