"""Augmentation of flow training batches (``model=flow_mix``): mirror, greyscale and photometric jitter.

Convention:
    Images (B,3,H,W) in [0,1]; flows (B,2,H,W) in pixels (u right, v down); validity (B,1,H,W) bool. A supervised
    batch is ``(img1, img2, flow_fwd, flow_bwd, valid_fwd, valid_bwd)`` with ``flow_fwd`` 1 -> 2 on image 1 and
    ``flow_bwd`` 2 -> 1 on image 2. Every draw comes from the ``torch.Generator`` passed in (the module seeds one per
    (data seed, step, DDP rank), so a resumed run draws the same), in a fixed order whatever the probabilities are.

Supervised pairs (:func:`augment_supervised`): with ``flip_prob`` the whole batch is mirrored (images, validity and
flows, u negated); each pair becomes greyscale (luma in all three channels, KITTI odometry's cameras) with
``gray_prob``; each image gets its own brightness x[0.8, 1.2], contrast x[0.8, 1.2] about its mean and gamma in
[0.8, 1.25] (``jitter``: exposure that changes between the two frames). Self-supervised pairs
(:func:`augment_self_supervised`): mirrored with ``flip_prob`` (the whole batch), greyscale per pair with
``kitti_gray_prob``; no jitter (the photometric loss compares the images themselves).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["FlowAugmentConfig", "LUMA", "photometric_jitter", "augment_supervised", "augment_self_supervised"]

LUMA = (0.299, 0.587, 0.114)


@dataclass
class FlowAugmentConfig:
    """``model.augment`` of flow training (see the module docstring).

    Attributes:
        flip_prob: probability that a batch is mirrored (drawn separately for the supervised and the KITTI part).
        gray_prob: probability that a supervised pair is greyscale.
        kitti_gray_prob: probability that a self-supervised (KITTI) pair is greyscale.
        jitter: per-image brightness, contrast and gamma of the supervised pairs.
    """

    flip_prob: float = 0.5
    gray_prob: float = 0.3
    kitti_gray_prob: float = 0.0
    jitter: bool = True

    def __post_init__(self) -> None:
        for key in ("flip_prob", "gray_prob", "kitti_gray_prob"):
            if not 0.0 <= float(getattr(self, key)) <= 1.0:
                raise ValueError(f"model.augment.{key}={getattr(self, key)}; expected a probability in [0, 1]")


def photometric_jitter(img: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """(N,3,H,W) images, each with its own brightness x[0.8,1.2], contrast x[0.8,1.2] (about its mean) and gamma in
    [0.8, 1.25]; values clamped to [1e-4, 1] before the gamma."""
    n = img.shape[0]
    r = torch.rand(n, 3, 1, 1, 1, generator=generator).to(img.device)
    brightness, contrast, gamma = 0.8 + 0.4 * r[:, 0], 0.8 + 0.4 * r[:, 1], torch.exp((r[:, 2] - 0.5) * 0.45)
    mean = img.mean((1, 2, 3), keepdim=True)
    return (((img - mean) * contrast + mean) * brightness).clamp(1e-4, 1).pow(gamma)


def _gray(x: torch.Tensor, gray: torch.Tensor) -> torch.Tensor:
    """``x`` (B,3,H,W) with the samples where ``gray`` (B,1,1,1) is 1 replaced by their luma."""
    luma = torch.tensor(LUMA, device=x.device, dtype=x.dtype).view(1, 3, 1, 1)
    return gray * (x * luma).sum(1, keepdim=True).expand_as(x) + (1 - gray) * x


def augment_supervised(img1: torch.Tensor, img2: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor,
                       valid_fwd: torch.Tensor, valid_bwd: torch.Tensor, cfg: FlowAugmentConfig,
                       generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    """Mirror (per batch), greyscale (per pair) and jitter (per image) a supervised batch; returns the six tensors
    in the order given. Draws: one flip, B greyscale, then (if ``cfg.jitter``) 2B x 3 jitter numbers."""
    if torch.rand((), generator=generator) < cfg.flip_prob:
        sign = torch.tensor([-1.0, 1.0], device=flow_fwd.device, dtype=flow_fwd.dtype).view(1, 2, 1, 1)
        img1, img2, valid_fwd, valid_bwd = img1.flip(-1), img2.flip(-1), valid_fwd.flip(-1), valid_bwd.flip(-1)
        flow_fwd, flow_bwd = flow_fwd.flip(-1) * sign, flow_bwd.flip(-1) * sign
    gray = (torch.rand(img1.shape[0], 1, 1, 1, generator=generator) < cfg.gray_prob).to(img1)
    both = torch.cat([_gray(img1, gray), _gray(img2, gray)])
    if cfg.jitter:
        both = photometric_jitter(both, generator)
    img1, img2 = both.split(img1.shape[0])
    return img1, img2, flow_fwd, flow_bwd, valid_fwd, valid_bwd


def augment_self_supervised(img1: torch.Tensor, img2: torch.Tensor, cfg: FlowAugmentConfig,
                            generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Mirror (per batch) and greyscale (per pair) a self-supervised batch of image pairs. Draws: one flip, then B
    greyscale."""
    if torch.rand((), generator=generator) < cfg.flip_prob:
        img1, img2 = img1.flip(-1), img2.flip(-1)
    gray = (torch.rand(img1.shape[0], 1, 1, 1, generator=generator) < cfg.kitti_gray_prob).to(img1)
    return _gray(img1, gray), _gray(img2, gray)
