"""Network sources: trained flow and depth checkpoints, loaded safely (tensors only, no pickled code).

Checkpoint files are read by :mod:`dfvo.io.checkpoint` (``.safetensors``, or weights-only ``.pt``/``.ckpt``).

Network input size:
    A network runs best at the resolution it was trained at (a correlation layer's search range is in pixels;
    depth cues are learnt at one scale). ``input_size=(h, w)`` resizes the images to that size before the network
    and resizes its output back (flow vectors scaled by the size ratios); ``None`` takes the checkpoint's
    ``height``/``width`` metadata when it has them (the export script writes them), else the images' own size.

Convention:
    Images (B,3,H,W) float in [0,1]; flow (B,2,H,W) in pixels of the input; depth (B,1,H,W) in metres after
    multiplying the network depth by ``depth_scale`` (5.4 for a monodepth2-style stereo model trained with a
    0.1 baseline on KITTI's 0.54 m rig; 1.0 for models trained with the true baseline or monocular ones).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.io.checkpoint import CheckpointError, load_weights, read_state_dict
from dfvo.models.depth_net import DepthNet
from dfvo.models.flow_net import FlowNet

__all__ = ["blend_flipped_inverse_depth", "NetworkFlow", "NetworkDepth", "resolve_input_size", "resize_images",
           "resize_flow"]

VARIANTS = ("default", "small", "tiny")


def resolve_input_size(input_size: Any, meta: dict[str, str], what: str) -> tuple[int, int] | None:
    """``(h, w)`` the network should see: ``input_size`` when given (a pair of positive ints), else the checkpoint
    metadata's ``height``/``width``, else None (the images' own size)."""
    if input_size is None:
        if "height" in meta and "width" in meta:
            return int(meta["height"]), int(meta["width"])
        return None
    try:
        h, w = (int(v) for v in input_size)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what}.input_size={input_size!r}; expected [height, width] or null") from err
    if h < 32 or w < 32:
        raise ValueError(f"{what}.input_size={input_size!r}; expected [height, width] of at least 32 pixels")
    return h, w


def resize_images(images: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Images (B,C,H,W) -> ``size`` (h, w) as the networks see them: antialiased bilinear (unchanged at that size)."""
    if tuple(images.shape[-2:]) == size:
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)


def resize_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Flow (B,2,h,w) in pixels of its own size → (B,2,H,W) in pixels of ``size``."""
    h, w = flow.shape[-2:]
    if (h, w) == tuple(size):
        return flow
    out = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
    scale = torch.tensor([size[1] / w, size[0] / h], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    return out * scale


class NetworkFlow:
    """Forward and backward flow from a trained :class:`~dfvo.models.flow_net.FlowNet` (one batch of 2B pairs).

    Args:
        checkpoint: weights file.
        variant: FlowNet variant; None: the checkpoint's ``variant`` metadata, else the first of
            :data:`VARIANTS` whose parameters match the checkpoint.
        device: torch device.
        input_size: (h, w) the network runs at (see module docstring); None: checkpoint metadata or image size.
    """

    name = "network"

    def __init__(self, checkpoint: str | Path, variant: str | None = None, device: str = "cpu",
                 input_size: Any = None) -> None:
        self.checkpoint = Path(checkpoint)
        meta = {}
        if self.checkpoint.is_file():
            _, meta = read_state_dict(self.checkpoint, "flow network", "flow.checkpoint")
        if variant is None and "variant" not in meta and self.checkpoint.is_file():
            variant = self._guess_variant(device)
        self.variant = variant or meta.get("variant", "default")
        self.model = FlowNet(self.variant).to(device).eval()
        load_weights(self.model, self.checkpoint, f"flow network FlowNet({self.variant!r})", "flow.checkpoint")
        self.device = torch.device(device)
        self.input_size = resolve_input_size(input_size, meta, "flow")

    def _guess_variant(self, device: str) -> str | None:
        """The first FlowNet variant whose parameters the checkpoint holds (None: none does; load_weights then
        reports the mismatch against the default variant)."""
        for name in VARIANTS:
            try:
                load_weights(FlowNet(name).to(device), self.checkpoint, f"flow network FlowNet({name!r})")
                return name
            except CheckpointError:
                continue
        return None

    def network_inputs(self, *images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The images (B,3,H,W) as the network sees them: on its device, resized to its input size."""
        return tuple(resize_images(im.to(self.device), self.input_size or tuple(im.shape[-2:])) for im in images)

    def __call__(self, images_prev: torch.Tensor, images_cur: torch.Tensor,
                 indices: list[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(flow_fwd, flow_bwd)`` (B,2,H,W) for images (B,3,H,W) prev and cur (``indices`` unused)."""
        KORNIA_CHECK_SHAPE(images_prev, ["B", "3", "H", "W"])
        size = tuple(images_prev.shape[-2:])
        with torch.no_grad():
            fwd, bwd = self.model.forward_backward(*self.network_inputs(images_prev, images_cur))
            return resize_flow(fwd, size), resize_flow(bwd, size)


def blend_flipped_inverse_depth(inv_depth: torch.Tensor, inv_depth_of_mirror: torch.Tensor,
                                border: float = 0.05) -> torch.Tensor:
    """Blend a prediction with the prediction for the mirrored image (mirrored back), both (B,1,H,W) inverse depth.

    The mean of the two, except near the left and right borders: a stereo-trained network is unreliable on the
    strip of the left image its right partner does not see (the left border), so there the mirrored prediction
    (whose unreliable strip is on the other side) takes over, fading linearly to the mean between ``border`` and
    ``2 * border`` of the width; symmetrically at the right border (monodepth's post-processing).
    """
    KORNIA_CHECK_SHAPE(inv_depth, ["B", "1", "H", "W"])
    KORNIA_CHECK(inv_depth_of_mirror.shape == inv_depth.shape,
                 f"blend_flipped_inverse_depth: shapes {tuple(inv_depth.shape)} and "
                 f"{tuple(inv_depth_of_mirror.shape)} differ")
    KORNIA_CHECK(0.0 < border <= 0.25, f"blend_flipped_inverse_depth: border={border}; expected (0, 0.25]")
    w = inv_depth.shape[-1]
    u = torch.linspace(0.0, 1.0, w, dtype=inv_depth.dtype, device=inv_depth.device)
    near_left = (1.0 - ((u - border) / border).clamp(0.0, 1.0)).view(1, 1, 1, w)
    near_right = near_left.flip(-1)
    mean = 0.5 * (inv_depth + inv_depth_of_mirror)
    return near_right * inv_depth + near_left * inv_depth_of_mirror + (1.0 - near_left - near_right) * mean


class NetworkDepth:
    """Depth from a trained :class:`~dfvo.models.depth_net.DepthNet`.

    Args:
        checkpoint: weights file.
        depth_scale: factor from the network's depth to metres (see module docstring).
        min_depth, max_depth: the network's depth range (as trained).
        device: torch device.
        input_size: (h, w) the network runs at (see module docstring); None: checkpoint metadata or image size
            rounded to multiples of 32.
        flip_average: also run the network on the mirrored images and blend the two inverse depths (monodepth's
            test-time post-processing; see :func:`blend_flipped_inverse_depth`); twice the network time.
    """

    name = "network"

    def __init__(self, checkpoint: str | Path, depth_scale: float = 1.0, min_depth: float = 0.1,
                 max_depth: float = 100.0, device: str = "cpu", input_size: Any = None,
                 flip_average: bool = False) -> None:
        if depth_scale <= 0:
            raise ValueError(f"depth.depth_scale={depth_scale}; expected a positive factor to metres")
        self.checkpoint = Path(checkpoint)
        self.model = DepthNet(min_depth, max_depth).to(device).eval()
        meta = load_weights(self.model, self.checkpoint, "depth network DepthNet", "depth.checkpoint")
        self.depth_scale = float(depth_scale)
        self.device = torch.device(device)
        self.input_size = resolve_input_size(input_size, meta, "depth")
        self.flip_average = bool(flip_average)

    def __call__(self, images: torch.Tensor, indices: list[int] | None = None) -> torch.Tensor:
        """Depth (B,1,H,W) in metres of images (B,3,H,W), computed at the network's input size (multiples of 32)
        and resized back."""
        KORNIA_CHECK_SHAPE(images, ["B", "3", "H", "W"])
        h, w = images.shape[-2:]
        nh, nw = self.input_size or (h, w)
        hp, wp = max(64, round(nh / 32) * 32), max(64, round(nw / 32) * 32)
        with torch.no_grad():
            inputs = resize_images(images.to(self.device), (hp, wp))
            if self.flip_average:
                both = self.model.depth(torch.cat([inputs, inputs.flip(-1)]))
                plain, mirrored = both.split(inputs.shape[0])
                depth = 1.0 / blend_flipped_inverse_depth(1.0 / plain, 1.0 / mirrored.flip(-1))
            else:
                depth = self.model.depth(inputs)
            if (hp, wp) != (h, w):
                depth = F.interpolate(depth, size=(h, w), mode="bilinear", align_corners=False)
            return depth * self.depth_scale
