"""Training-time augmentation of depth/pose batches: horizontal flips and colour jitter (monodepth2's recipe), and
cast shadows on the depth network's input.

Convention:
    A batch holds ``image`` (B,3,H,W) and, as the task needs, ``image_prev``, ``image_next``, ``image_right``
    (B,3,H,W) in [0,1], ``K`` (B,3,3) in pixels of the batch's resolution and ``T_right_left`` (B,4,4) with
    translation ``(-b, 0, 0)``. Pixel centres are at integer coordinates (:mod:`dfvo.geometry.camera`).

    - **Flip** (geometry, changes what the losses see): every image of a sample is mirrored left-right, so
      ``u -> W-1-u`` and ``cx -> W-1-cx``. Mirroring the world about the left camera's x = 0 plane
      (``M = diag(-1, 1, 1, 1)``) turns ``T_right_left`` into ``M T_right_left M``: for a rectified rig the right
      camera moves to ``-b`` (the x translation changes sign), with no left/right swap, so the temporal neighbours
      stay the left camera's. The pose network is trained on the mirrored pairs as they are.
    - **Colour jitter** (appearance, the network inputs only): brightness and contrast factors in
      ``[1-a, 1+a]``, saturation in ``[1-a, 1+a]``, hue shift in ``[-h, h]`` turns, the same for every image
      of a sample so the frames stay photometrically consistent; with ``gray_prob`` a sample's inputs become
      greyscale (KITTI odometry's cameras 0/1 are greyscale). The photometric losses compare the un-jittered
      images, as monodepth2 does.
    - **Shadows** (appearance, the depth network's input only): with ``shadow_prob`` a sample's ``image`` gets one
      to three soft-edged dark regions (half-planes across the image or rotated ellipses, each darkening by a
      factor in ``shadow_factor``), as trees and buildings cast them on a sunny road. The depth does not change
      under a shadow, so the network has to learn that a dark patch of road is still road (measured: the networks
      trained on drive 0001 and the synthetic worlds moved their road plane by up to 30-39 % for one darkened patch
      of a KITTI 07 frame, the shipped one by up to 8 %: docs/training.md). The pose network sees the images without
      shadows (a shadow that moved with the camera would be a false motion cue), and the losses compare the images
      as they are.

Random draws come from a ``torch.Generator`` the caller seeds (the depth module seeds it with the data seed and
the global step), so a resumed run draws the same augmentations as an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.enhance import adjust_hue, adjust_saturation

__all__ = ["DepthAugmentConfig", "IMAGE_KEYS", "flip_batch", "jitter_images", "shadow_masks", "cast_shadows",
           "augment_depth_batch"]

IMAGE_KEYS = ("image", "image_prev", "image_next", "image_right")
LUMA = (0.299, 0.587, 0.114)


@dataclass
class DepthAugmentConfig:
    """Augmentation settings (``model.augment`` in ``conf/model/depth_*.yaml``; monodepth2's values).

    Attributes:
        flip_prob: probability of mirroring a sample.
        jitter_prob: probability of colour-jittering a sample's network inputs.
        brightness, contrast, saturation: factors are drawn uniformly from ``[1-a, 1+a]``.
        hue: hue shift drawn uniformly from ``[-hue, hue]`` in turns (0.1 = 36 degrees).
        gray_prob: probability of greyscale network inputs.
        shadow_prob: probability of casting shadows on a sample's depth-network input (0: off, the default).
        shadow_factor: (low, high) range of the brightness factor inside a shadow (0.4 keeps 40 % of the light).
    """

    flip_prob: float = 0.5
    jitter_prob: float = 0.5
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.1
    gray_prob: float = 0.0
    shadow_prob: float = 0.0
    shadow_factor: tuple[float, float] = (0.35, 0.75)

    def __post_init__(self) -> None:
        values = list(self.shadow_factor)
        lo, hi = (float(values[0]), float(values[1])) if len(values) == 2 else (-1.0, -1.0)
        if not 0.0 < lo <= hi <= 1.0:
            raise ValueError(f"model.augment.shadow_factor={list(self.shadow_factor)}; expected [low, high] with "
                             "0 < low <= high <= 1")
        for name in ("flip_prob", "jitter_prob", "gray_prob", "shadow_prob"):
            value = float(getattr(self, name))
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"model.augment.{name}={value}; expected a probability in [0, 1]")
        for name in ("brightness", "contrast", "saturation"):
            value = float(getattr(self, name))
            if not 0.0 <= value < 1.0:
                raise ValueError(f"model.augment.{name}={value}; expected a factor range in [0, 1)")
        if not 0.0 <= float(self.hue) <= 0.5:
            raise ValueError(f"model.augment.hue={self.hue}; expected a hue range in [0, 0.5] turns")


def flip_batch(batch: dict[str, torch.Tensor], flip: torch.Tensor) -> dict[str, torch.Tensor]:
    """Mirror the samples where ``flip`` (B,) is True: images, ``K`` and ``T_right_left`` (see module docstring).

    Returns a new dict; keys other than images, ``K`` and ``T_right_left`` are passed through unchanged (a
    ``depth`` map or ``depth_hint``, if present, is mirrored too).
    """
    image = batch["image"]
    KORNIA_CHECK_SHAPE(image, ["B", "3", "H", "W"])
    KORNIA_CHECK(flip.shape == (image.shape[0],), f"flip_batch: flip must be (B,)=({image.shape[0]},), "
                                                  f"got {tuple(flip.shape)}")
    if not bool(flip.any()):
        return dict(batch)
    W = image.shape[-1]
    out = dict(batch)
    f = flip.to(image.device)
    for key in (*IMAGE_KEYS, "depth", "depth_hint"):
        if key in batch:
            x = batch[key]
            out[key] = torch.where(f.view(-1, 1, 1, 1), x.flip(-1), x)
    if "K" in batch:
        K = batch["K"].clone()
        K[:, 0, 2] = torch.where(f, (W - 1) - K[:, 0, 2], K[:, 0, 2])
        out["K"] = K
    if "T_right_left" in batch:
        T = batch["T_right_left"]
        M = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=T.dtype, device=T.device))
        out["T_right_left"] = torch.where(f.view(-1, 1, 1), M @ T @ M, T)
    return out


def _uniform(n: int, half_width: float, generator: torch.Generator, centre: float = 0.0) -> torch.Tensor:
    return centre + (2.0 * torch.rand(n, generator=generator, dtype=torch.float64) - 1.0) * half_width


def jitter_images(images: dict[str, torch.Tensor], cfg: DepthAugmentConfig,
                  generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Colour-jittered copies of ``images`` (each (B,3,H,W) in [0,1]); one draw per sample, shared by its images.

    Order: brightness, contrast (about the image's mean grey), saturation, hue, then greyscale; values are
    clamped to [0,1].
    """
    first = next(iter(images.values()))
    B = first.shape[0]
    dev, dt = first.device, first.dtype
    jit = torch.rand(B, generator=generator, dtype=torch.float64) < cfg.jitter_prob
    bright = torch.where(jit, _uniform(B, cfg.brightness, generator, 1.0), 1.0)
    contrast = torch.where(jit, _uniform(B, cfg.contrast, generator, 1.0), 1.0)
    sat = torch.where(jit, _uniform(B, cfg.saturation, generator, 1.0), 1.0)
    hue = torch.where(jit, _uniform(B, cfg.hue, generator), 0.0) * (2.0 * math.pi)  # turns -> radians
    gray = torch.rand(B, generator=generator, dtype=torch.float64) < cfg.gray_prob
    luma = torch.tensor(LUMA, device=dev, dtype=dt).view(1, 3, 1, 1)
    view = lambda v: v.to(device=dev, dtype=dt).view(-1, 1, 1, 1)  # noqa: E731
    out = {}
    for key, img in images.items():
        x = (img * view(bright)).clamp(0, 1)
        mean = (x * luma).sum(1, keepdim=True).mean(dim=(2, 3), keepdim=True)
        x = (mean + view(contrast) * (x - mean)).clamp(0, 1)
        x = adjust_saturation(x, sat.to(device=dev, dtype=dt))
        x = adjust_hue(x, hue.to(device=dev, dtype=dt)).clamp(0, 1)
        g = (x * luma).sum(1, keepdim=True).expand_as(x)
        out[key] = torch.where(view(gray.to(torch.float64)) > 0, g, x)
    return out


def shadow_masks(B: int, H: int, W: int, generator: torch.Generator, max_shapes: int = 3) -> torch.Tensor:
    """(B,1,H,W) float64 in [0,1]: how much of each pixel lies in shadow (1 inside, 0 outside, a linear edge ramp
    0.5-3 px wide).

    Each sample gets 1..``max_shapes`` shapes, each the half-plane below a line through a random point at a random
    angle (the side the line's normal, drawn in [0, pi), points to: the lower one, as on the ground) or an ellipse
    (semi-axes 5-40 % of the width and 5-30 % of the height, random rotation) centred anywhere in the image; the union
    is the per-pixel maximum.
    """
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    n_shapes = torch.randint(1, max_shapes + 1, (B,), generator=generator)
    draw = lambda *shape: torch.rand(*shape, generator=generator, dtype=torch.float64)  # noqa: E731
    kind, cu, cv, angle = draw(B, max_shapes) < 0.5, draw(B, max_shapes) * W, draw(B, max_shapes) * H, \
        draw(B, max_shapes) * math.pi
    a = (0.05 + 0.35 * draw(B, max_shapes)) * W
    b = (0.05 + 0.25 * draw(B, max_shapes)) * H
    edge = 0.5 + 2.5 * draw(B, max_shapes)
    mask = torch.zeros(B, 1, H, W, dtype=torch.float64)
    for k in range(max_shapes):
        c, s = torch.cos(angle[:, k]).view(B, 1, 1), torch.sin(angle[:, k]).view(B, 1, 1)
        du, dv = u - cu[:, k].view(B, 1, 1), v - cv[:, k].view(B, 1, 1)
        plane = (du * c + dv * s) / edge[:, k].view(B, 1, 1)  # signed distance to the line, in edge widths
        x, y = (du * c + dv * s) / a[:, k].view(B, 1, 1), (-du * s + dv * c) / b[:, k].view(B, 1, 1)
        r = torch.sqrt(x * x + y * y)  # 1 on the ellipse
        inside = (1.0 - r) * torch.minimum(a[:, k], b[:, k]).view(B, 1, 1) / edge[:, k].view(B, 1, 1)
        shape = (0.5 + torch.where(kind[:, k].view(B, 1, 1), plane, inside)).clamp(0.0, 1.0)  # linear edge ramp
        used = (k < n_shapes).to(torch.float64).view(B, 1, 1)
        mask[:, 0] = torch.maximum(mask[:, 0], shape * used)
    return mask


def cast_shadows(image: torch.Tensor, cfg: DepthAugmentConfig, generator: torch.Generator) -> torch.Tensor:
    """``image`` (B,3,H,W) in [0,1] with shadows cast on the samples drawn with ``cfg.shadow_prob``: each pixel is
    multiplied by ``1 - (1 - f) m`` (``m`` of :func:`shadow_masks`, ``f`` drawn from ``cfg.shadow_factor`` per
    sample); the other samples are returned unchanged."""
    B, _, H, W = image.shape
    use = torch.rand(B, generator=generator, dtype=torch.float64) < cfg.shadow_prob
    lo, hi = (float(x) for x in cfg.shadow_factor)
    factor = lo + (hi - lo) * torch.rand(B, generator=generator, dtype=torch.float64)
    if not bool(use.any()):
        return image
    mask = shadow_masks(B, H, W, generator)
    gain = 1.0 - (1.0 - factor).view(B, 1, 1, 1) * mask * use.to(torch.float64).view(B, 1, 1, 1)
    return image * gain.to(device=image.device, dtype=image.dtype)


def augment_depth_batch(batch: dict[str, torch.Tensor], cfg: DepthAugmentConfig, generator: torch.Generator
                        ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Flip (geometry) then jitter (network inputs) a depth/pose training batch, and cast shadows on the depth
    network's input (``cfg.shadow_prob`` > 0).

    Returns:
        ``(batch, net_inputs)``: the (possibly mirrored) batch the losses use, and the jittered images
        ``{key: (B,3,H,W)}`` for every image key present, which the depth and pose networks see; the depth
        network's ``image_depth`` is ``image`` with its shadows (only when ``cfg.shadow_prob`` > 0).
    """
    B = batch["image"].shape[0]
    flip = torch.rand(B, generator=generator, dtype=torch.float64) < cfg.flip_prob
    batch = flip_batch(batch, flip)
    images = {k: batch[k] for k in IMAGE_KEYS if k in batch}
    net_inputs = jitter_images(images, cfg, generator)
    if cfg.shadow_prob > 0:  # drawn after the jitter: runs without shadows keep their random stream
        net_inputs["image_depth"] = cast_shadows(net_inputs["image"], cfg, generator)
    return batch, net_inputs
