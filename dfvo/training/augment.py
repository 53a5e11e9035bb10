"""Training-time augmentation of depth/pose batches: horizontal flips and colour jitter (monodepth2's recipe), cast
shadows on the depth network's input, and objects pasted into stereo pairs at a known depth.

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
    - **Pasted objects** (geometry and appearance, every view of the stereo pair): with ``paste_prob`` a real sample
      (one with a known ``camera_height`` > 0: the KITTI samples of a mixed batch) gets 1..``paste_max`` upright
      rectangles facing the camera, each at a depth ``Z`` drawn log-uniformly from ``paste_depth`` (metres),
      ``paste_width`` wide and ``paste_height`` tall (metres), standing on the road: its lower edge at the row ``cy +
      fy h / Z`` of a level camera ``h`` above the ground, its centre at a random column. Its texture is a crop of one
      of the batch's images at a random place (within ``paste_source_rows`` of its height), ``paste_texture_scale``
      source pixels per object pixel (as large as the image at most), so near and far objects show a real image's
      detail alike (a near object made of a magnified small crop would be a blur, and teach that blur is near), scaled
      by a brightness factor in ``paste_gain``. The same rectangle is drawn into the right image shifted by the pair's
      disparity ``fx t_x / Z`` (a plane parallel to the image plane of a rectified pair maps by that shift), so the
      stereo loss sees a consistent object, and ``depth`` (created, 0 = no truth, when the batch has none) is set to
      ``Z`` on its pixels, which ``model.w_depth_supervised`` supervises. Nearer objects are drawn last (they occlude
      farther ones); an object hides whatever the image showed there, even something nearer. The temporal views
      (``image_prev``, ``image_next``) are left without it: pasting is meant for stereo training
      (``model.temporal=false``); with temporal views the per-pixel minimum over views picks the stereo partner there.
      Why: the networks trained on drive 0001 draw large near objects of little texture (a van 3-6 m away) far away on
      the held-out drive 0005 (docs/training.md); one drive has few of them.

Random draws come from a ``torch.Generator`` the caller seeds (the depth module seeds it with the data seed and
the global step), so a resumed run draws the same augmentations as an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.enhance import adjust_hue, adjust_saturation

__all__ = ["DepthAugmentConfig", "IMAGE_KEYS", "flip_batch", "jitter_images", "shadow_masks", "cast_shadows",
           "paste_objects", "augment_depth_batch"]

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
        paste_prob: probability of pasting objects into a real sample's stereo pair (0: off, the default).
        paste_max: at most this many objects a sample (1..paste_max drawn uniformly).
        paste_depth: (near, far) metres, drawn log-uniformly.
        paste_width, paste_height: (low, high) metres, drawn uniformly.
        paste_gain: (low, high) brightness factor of an object's texture.
        paste_texture_scale: (low, high) source-image pixels per object pixel of its texture, drawn log-uniformly.
        paste_source_rows: (top, bottom) fractions of the source image's height the texture crops come from
            ([0.5, 1]: its lower half, where a road camera sees what is near).
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
    paste_prob: float = 0.0
    paste_max: int = 2
    paste_depth: tuple[float, float] = (3.0, 20.0)
    paste_width: tuple[float, float] = (1.5, 6.0)
    paste_height: tuple[float, float] = (1.0, 3.0)
    paste_gain: tuple[float, float] = (0.3, 1.1)
    paste_texture_scale: tuple[float, float] = (0.5, 2.0)
    paste_source_rows: tuple[float, float] = (0.0, 1.0)

    def __post_init__(self) -> None:
        values = list(self.shadow_factor)
        lo, hi = (float(values[0]), float(values[1])) if len(values) == 2 else (-1.0, -1.0)
        if not 0.0 < lo <= hi <= 1.0:
            raise ValueError(f"model.augment.shadow_factor={list(self.shadow_factor)}; expected [low, high] with "
                             "0 < low <= high <= 1")
        for name in ("paste_depth", "paste_width", "paste_height", "paste_gain", "paste_texture_scale"):
            values = list(getattr(self, name))
            lo, hi = (float(values[0]), float(values[1])) if len(values) == 2 else (-1.0, -1.0)
            if not 0.0 < lo <= hi:
                raise ValueError(f"model.augment.{name}={values}; expected [low, high] with 0 < low <= high")
        values = list(self.paste_source_rows)
        lo, hi = (float(values[0]), float(values[1])) if len(values) == 2 else (-1.0, -1.0)
        if not 0.0 <= lo < hi <= 1.0:
            raise ValueError(f"model.augment.paste_source_rows={values}; expected [top, bottom] fractions with "
                             "0 <= top < bottom <= 1")
        if int(self.paste_max) < 1:
            raise ValueError(f"model.augment.paste_max={self.paste_max}; expected at least 1 object a sample")
        for name in ("flip_prob", "jitter_prob", "gray_prob", "shadow_prob", "paste_prob"):
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


def _draw(n: int, bounds: tuple[float, float], generator: torch.Generator, log: bool = False) -> torch.Tensor:
    lo, hi = (float(x) for x in bounds)
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))) if log else lo + u * (hi - lo)


def paste_objects(batch: dict[str, torch.Tensor], cfg: DepthAugmentConfig, generator: torch.Generator
                  ) -> dict[str, torch.Tensor]:
    """``batch`` with objects pasted into the stereo pairs of the real samples drawn with ``cfg.paste_prob`` (module
    docstring): ``image`` and ``image_right`` (B,3,H,W) get the objects, ``depth`` (B,1,H,W) their depth ``Z`` on
    their pixels (created with 0 = no truth elsewhere when the batch has none). Needs ``K`` (B,3,3),
    ``T_right_left`` (B,4,4) of a rectified pair (no rotation) and ``camera_height`` (B,) metres (> 0 marks a real
    sample; a batch without it has no real sample and is returned as it is: the depth module checks that the data
    gives the height). When anything is pasted, ``pasted`` (B,1,H,W) bool marks the left image's object pixels,
    ``image_unpasted`` (B,3,H,W) keeps the left image as it was (the distillation teacher's view) and a
    ``depth_hint`` (B,1,H,W) loses its hints on the objects (0: none). Returns a new dict; the input is not
    modified."""
    if "camera_height" not in batch:  # no real sample in this batch (a mixed batch of synthetic samples alone)
        return dict(batch)
    for key in ("image_right", "T_right_left", "K"):
        if key not in batch:
            raise ValueError(f"model.augment.paste_prob={cfg.paste_prob}: the batch has no {key!r}; pasted objects "
                             "need stereo pairs (model.stereo=true) and K")
    image, right, K, T = batch["image"], batch["image_right"], batch["K"], batch["T_right_left"]
    KORNIA_CHECK_SHAPE(image, ["B", "3", "H", "W"])
    B, _, H, W = image.shape
    height = batch["camera_height"].reshape(B)
    use = (torch.rand(B, generator=generator, dtype=torch.float64) < cfg.paste_prob) & (height.cpu() > 0)
    count = torch.randint(1, int(cfg.paste_max) + 1, (B,), generator=generator)
    n = int(cfg.paste_max)
    Z, width = _draw(B * n, cfg.paste_depth, generator, log=True), _draw(B * n, cfg.paste_width, generator)
    tall, gain = _draw(B * n, cfg.paste_height, generator), _draw(B * n, cfg.paste_gain, generator)
    centre = torch.rand(B * n, generator=generator, dtype=torch.float64) * (W - 1)
    source = torch.randint(0, B, (B * n,), generator=generator)
    magnify = _draw(B * n, cfg.paste_texture_scale, generator, log=True)  # source pixels per object pixel
    place = torch.rand(B * n, 2, generator=generator, dtype=torch.float64)  # where the crop lies in its image
    if not bool(use.any()):
        return dict(batch)
    rotation = T[:, :3, :3].double().cpu() - torch.eye(3, dtype=torch.float64)
    KORNIA_CHECK(bool((rotation[use].abs() <= 1e-4).all()), "model.augment.paste_prob > 0 needs rectified stereo "
                 "pairs (T_right_left without rotation)")
    out = dict(batch)
    pasted = torch.zeros(B, 1, H, W, dtype=torch.bool, device=image.device)
    depth = batch.get("depth")
    depth = torch.zeros(B, 1, H, W, dtype=image.dtype, device=image.device) if depth is None else depth.clone()
    views = {"image": image.clone(), "image_right": right.clone()}
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    Kd, Td = K.double().cpu(), T.double().cpu()
    top_row, bottom_row = (float(x) for x in cfg.paste_source_rows)
    for b in torch.nonzero(use).flatten().tolist():
        fx, fy, cy = float(Kd[b, 0, 0]), float(Kd[b, 1, 1]), float(Kd[b, 1, 2])
        objects = sorted(range(b * n, b * n + int(count[b])), key=lambda k: -float(Z[k]))  # far first
        for k in objects:
            z = float(Z[k])
            half = 0.5 * fx * float(width[k]) / z
            bottom = cy + fy * float(height[b]) / z
            top = bottom - fy * float(tall[k]) / z
            t = (v - top) / (bottom - top)  # 0..1 down the object
            # the texture crop (fractions of the source image): the object's own size in pixels times the draw, so
            # its texture keeps a real image's detail at every depth (a near object is not a magnified blur)
            crop = [min(1.0, 2.0 * half * float(magnify[k]) / (W - 1)),
                    min(1.0, (bottom - top) * float(magnify[k]) / (H - 1))]
            crop[1] = min(crop[1], bottom_row - top_row)
            corner = [float(place[k, 0]) * (1.0 - crop[0]),
                      top_row + float(place[k, 1]) * (bottom_row - top_row - crop[1])]
            for key, shift in (("image", 0.0), ("image_right", fx * float(Td[b, 0, 3]) / z)):
                s = (u - shift - (float(centre[k]) - half)) / (2.0 * half)  # 0..1 across the object
                inside = (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
                if not bool(inside.any()):
                    continue
                x = (corner[0] + s * crop[0]) * 2.0 - 1.0  # grid_sample units, align_corners=True
                y = (corner[1] + t * crop[1]) * 2.0 - 1.0
                grid = torch.stack([x, y], -1)[None].to(device=image.device, dtype=image.dtype)
                texture = F.grid_sample(image[int(source[k])][None], grid, mode="bilinear", align_corners=True)[0]
                texture = (texture * float(gain[k])).clamp(0, 1)
                mask = inside.to(image.device)
                views[key][b] = torch.where(mask, texture, views[key][b])
                if key == "image":
                    depth[b, 0] = torch.where(mask, torch.full_like(depth[b, 0], z), depth[b, 0])
                    pasted[b, 0] |= mask
    out.update(views)
    out["depth"] = depth
    if "depth_hint" in batch:  # the stereo matcher measured the scene the objects now hide: no hint there
        out["depth_hint"] = batch["depth_hint"].masked_fill(pasted, 0.0)
    out["pasted"] = pasted
    out["image_unpasted"] = image
    return out


def augment_depth_batch(batch: dict[str, torch.Tensor], cfg: DepthAugmentConfig, generator: torch.Generator
                        ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Flip (geometry), paste objects (``cfg.paste_prob`` > 0), then jitter (network inputs) a depth/pose training
    batch, and cast shadows on the depth network's input (``cfg.shadow_prob`` > 0).

    Returns:
        ``(batch, net_inputs)``: the (possibly mirrored) batch the losses use, and the jittered images
        ``{key: (B,3,H,W)}`` for every image key present, which the depth and pose networks see; the depth
        network's ``image_depth`` is ``image`` with its shadows (only when ``cfg.shadow_prob`` > 0); when objects
        were pasted, ``image_unpasted`` is ``image`` without them, jittered alike (the teacher's view).
    """
    B = batch["image"].shape[0]
    flip = torch.rand(B, generator=generator, dtype=torch.float64) < cfg.flip_prob
    batch = flip_batch(batch, flip)
    if cfg.paste_prob > 0:  # drawn only when on: runs without pasted objects keep their random stream
        batch = paste_objects(batch, cfg, generator)
    images = {k: batch[k] for k in (*IMAGE_KEYS, "image_unpasted") if k in batch}
    net_inputs = jitter_images(images, cfg, generator)  # one draw per sample, whatever the keys
    if cfg.shadow_prob > 0:  # drawn after the jitter: runs without shadows keep their random stream
        net_inputs["image_depth"] = cast_shadows(net_inputs["image"], cfg, generator)
    return batch, net_inputs
