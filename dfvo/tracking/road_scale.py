"""Photometric road scale: how far below the camera the road is, in the unit of the E-tracker's translation.

A plane ``n . X = d`` (camera i's frame, unit normal ``n`` pointing down, ``d`` the camera's height above it) maps the
pixels of image i into image j through the homography ``K (R + t n^T / d) K^-1`` of ``T_cur_prev = [R | t]``. With the
E-tracker's unit translation ``t`` and rotation ``R`` known, only ``d`` (in the unit of ``t``) is left; it is found by
aligning a patch of road ahead of the car between the two images (zero-mean normalised cross-correlation over a log
grid of ``d`` around the expected value, or covering every plausible speed when nothing is expected or nothing is
found near it, refined by a parabola). The camera's height in metres over ``d`` is then the
translation's metric length: a scale observation that uses neither the flow (the learned flow is poorest on the
textureless road) nor the depth network's metric scale (whose bias changes with distance and road), only its plane
orientation to place the patch and to fix ``n``.

The patch is the road ahead of the camera between ``min_depth`` and ``max_depth`` metres and within ``half_width``
metres of the camera's line of sight, placed with the depth network's road plane (normal and height; the pitch
replaced by the motion's with ``normal_from_motion``, the height by the camera's known or estimated one when the
network's is implausible: ``max_height_ratio``); it is split
into blocks (near/far x left/centre/right) whose cost profiles are averaged over the blocks that align well (a car
or a shadow edge in one block does not move the optimum). Results with a poor best cost, an optimum at the edge of
the search range, or too few pixels are not used (``reason`` says why).

Convention:
    Grey images (1,1,H,W) float in [0,1] of the earlier (i) and later (j) frame; ``K`` (3,3); ``R`` (3,3) and unit
    ``t`` (3,) of ``T_cur_prev``; ``normal`` (3,) unit, pointing down (``n_y > 0``), in camera i; heights in metres
    (network units) for the patch, in the unit of ``t`` for the result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import torch
import torch.nn.functional as F

from dfvo.tracking.config import RoadAlignmentConfig

__all__ = ["RoadAlignment", "road_patch", "align_road"]


@dataclass
class RoadAlignment:
    """The road plane's distance ``unit_height`` below camera i in the unit of ``t`` (None when not found),
    ``cost`` (1 - ZNCC at the optimum, mean over the blocks used), ``blocks`` (blocks used) and ``reason`` (why
    nothing was found)."""

    unit_height: float | None
    cost: float | None
    blocks: int
    reason: str | None = None


@lru_cache(maxsize=4)
def _pixel_rays(k: tuple[float, ...], height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(HW,2) float64 pixels (x, y) of an image and their rays (HW,3) ``K^-1 (x, y, 1)`` (z = 1) for the 9 entries
    ``k`` of K; cached (the same camera every frame), never modified."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    px = torch.stack([u.flatten(), v.flatten()], -1)
    K_inv = torch.linalg.inv(torch.tensor(k, dtype=torch.float64).view(3, 3))
    rays = torch.cat([px, torch.ones_like(px[:, :1])], -1) @ K_inv.T
    return px, rays


def road_patch(K: torch.Tensor, normal: torch.Tensor, height: float, image_hw: tuple[int, int],
               cfg: RoadAlignmentConfig, ahead: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels of the road patch ahead and their block ids.

    Args:
        K: (3,3). normal: (3,) unit road normal (down) in the camera frame. height: the camera's height above that
            plane (metres, the depth network's). image_hw: (H, W). ahead: the patch starts and ends this many
            metres further (the expected travel: its road stays in view in the later image).

    Returns:
        pixels (N,2) float64 (x, y) of the pixels whose ray meets the plane between ``cfg.min_depth + ahead`` and
        ``cfg.max_depth + ahead`` metres ahead (camera z) and within ``cfg.half_width`` metres sideways, and (N,)
        long block ids: ``near/far`` (split at the middle depth) x ``left/centre/right`` (thirds of the width).
    """
    px, rays = _pixel_rays(tuple(K.to(torch.float64).reshape(-1).tolist()), *image_hw)
    den = rays @ normal.to(torch.float64)
    z = torch.where(den > 1e-9, height / den.clamp_min(1e-9), torch.full_like(den, float("inf")))
    x = rays[:, 0] * z
    z_lo, z_hi = cfg.min_depth + ahead, cfg.max_depth + ahead
    keep = (z >= z_lo) & (z <= z_hi) & (x.abs() <= cfg.half_width)
    far = (z[keep] > 0.5 * (z_lo + z_hi)).long()
    side = torch.bucketize(x[keep], torch.tensor([-cfg.half_width / 3, cfg.half_width / 3], dtype=torch.float64))
    return px[keep], far * 3 + side


def _cost_profiles(grey_prev: torch.Tensor, grey_cur: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                   normal: torch.Tensor, pixels: torch.Tensor, blocks: torch.Tensor,
                   log_heights: torch.Tensor) -> torch.Tensor:
    """(6,S) 1 - ZNCC of each block between image i's patch and image j sampled through the plane homography of
    each of the S heights ``exp(log_heights)`` (NaN for a block with too few pixels inside image j)."""
    H, W = grey_prev.shape[-2:]
    f64 = torch.float64
    Kd, Rd, td, n = K.to(f64), R.to(f64), t.to(f64), normal.to(f64)
    rays = torch.cat([pixels, torch.ones_like(pixels[:, :1])], -1) @ torch.linalg.inv(Kd).T  # (N,3)
    # the patch's own pixels sit at integer positions: read, not interpolated; both images' intensities less the
    # patch's mean, so that the float32 sums below cancel little (ZNCC does not depend on the offset)
    ref = grey_prev[0, 0, pixels[:, 1].long(), pixels[:, 0].long()].to(torch.float32)  # (N,)
    offset = ref.mean()
    ref = ref - offset
    # x_j ~ K (R r + t (n.r) / h), with K followed by the pixels -> grid_sample units map (align_corners=True), so
    # the homogeneous division gives the sampling grid directly; the rotated rays and K t in float64, the (S,N)
    # planes in float32 (1e-4 px)
    to_grid = torch.tensor([[2.0 / (W - 1), 0.0, -1.0], [0.0, 2.0 / (H - 1), -1.0], [0.0, 0.0, 1.0]], dtype=f64)
    Kg = to_grid @ Kd
    rotated = (rays @ (Kg @ Rd).T).to(torch.float32)  # (N,3)
    kt = (Kg @ td).tolist()
    along = ((rays @ n)[None] / log_heights.exp()[:, None]).to(torch.float32)  # (S,N)
    z = torch.add(rotated[:, 2], along, alpha=kt[2])  # (S,N)
    inv_z = z.clamp_min(1e-12).reciprocal_()
    grid = torch.stack([torch.add(rotated[:, 0], along, alpha=kt[0]).mul_(inv_z),
                        torch.add(rotated[:, 1], along, alpha=kt[1]).mul_(inv_z)], -1)  # (S,N,2)
    S = grid.shape[0]
    planes = torch.empty((3, S, grid.shape[1]), dtype=torch.float32)  # w, w s, w s^2
    torch.logical_and(grid.abs().amax(-1) <= 1.0, z > 0, out=planes[0])
    moved = F.grid_sample(grey_cur, grid[None], mode="bilinear", align_corners=True,
                          padding_mode="border")[0, 0].to(torch.float32).sub_(offset)  # (S,N)
    torch.mul(planes[0], moved, out=planes[1])
    torch.mul(planes[1], moved, out=planes[2])
    # per block, over the pixels inside image j: ZNCC = cov(a, s) / sqrt(var(a) var(s)), from the block sums of w,
    # w a, w a^2, w s, w s^2, w a s: one matrix product of [w; w s; w s^2] (3S,N) with [1, a, a^2] x the block
    # indicator (N,18); the covariances from them in float64
    onehot = F.one_hot(blocks, 6).to(torch.float32)  # (N,6)
    size = onehot.sum(0).to(f64)  # (6,)
    weights = torch.cat([onehot, onehot * ref[:, None], onehot * (ref * ref)[:, None]], 1)  # (N,18)
    sums = (planes.view(3 * S, -1) @ weights).view(3, S, 18).to(f64)
    cnt, sa, saa = sums[0].split(6, -1)
    ss, sas = sums[1, :, :6], sums[1, :, 6:12]
    sss = sums[2, :, :6]
    den = cnt.clamp_min(1.0)
    cov, var_a, var_s = sas - sa * ss / den, saa - sa * sa / den, sss - ss * ss / den
    textured = (var_a > 1e-8 * den) & (var_s > 1e-8 * den)  # a flat patch (no texture, or rounding) matches nothing
    zncc = torch.where(textured, cov / (var_a * var_s).clamp_min(1e-30).sqrt(), torch.zeros_like(cov))
    valid = (size >= 50)[None] & (cnt >= 0.5 * size[None])
    return torch.where(valid, 1.0 - zncc, torch.full_like(zncc, float("nan"))).T  # (6,S)


def _parabola_min(cost: torch.Tensor, log_heights: torch.Tensor) -> tuple[float, float, bool]:
    """The minimum of a sampled cost profile (its log height refined by a parabola through the best three samples),
    its cost, and whether it lies on the edge of the range."""
    i = int(torch.nan_to_num(cost, nan=float("inf")).argmin())
    step = float(log_heights[1] - log_heights[0]) if log_heights.numel() > 1 else 0.0
    if i == 0 or i == cost.numel() - 1:
        return float(log_heights[i]), float(cost[i]), True
    c0, c1, c2 = (float(cost[j]) for j in (i - 1, i, i + 1))
    den = c0 - 2 * c1 + c2
    off = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    return float(log_heights[i]) + max(-0.5, min(0.5, off)) * step, c1, False


def align_road(grey_prev: torch.Tensor, grey_cur: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
               normal: torch.Tensor, height: float, cfg: RoadAlignmentConfig,
               prior_unit_height: float | None = None) -> RoadAlignment:
    """The road's distance below camera i in the unit of ``t`` (see the module docstring).

    Args:
        grey_prev, grey_cur: (1,1,H,W). K: (3,3). R: (3,3), t: (3,) unit, of ``T_cur_prev``. normal: (3,) the road
            normal (down) and ``height`` its distance in metres, from the depth network (or the camera height when
            the network's is implausible); they place the patch.
        prior_unit_height: the expected result (the camera height over the filter's predicted length): searched first
            within ``cfg.span`` either way; when nothing is found there (or None), the whole ``cfg.wide_range``.
    """
    if not (math.isfinite(height) and height > 0):
        return RoadAlignment(None, None, 0, f"no road plane to place the patch (height {height})")
    if cfg.normal_from_motion:  # the car moves along its road: no normal component along the translation
        td = t.to(torch.float64).reshape(3)
        normal = normal.to(torch.float64) - (normal.to(torch.float64) @ td) * td
        normal = normal / normal.norm().clamp_min(1e-12)
    if not float(normal[1]) >= 0.5 * float(normal.norm()):
        return RoadAlignment(None, None, 0, "the road normal does not point down (over 60 deg from the camera's y)")
    lo, hi = math.log(cfg.wide_range[0]), math.log(cfg.wide_range[1])
    hw = tuple(grey_prev.shape[-2:])
    if prior_unit_height is not None and prior_unit_height > 0 and math.isfinite(prior_unit_height):
        # the patch moved ahead by the expected travel, so that its road is still in view in the later image
        ahead = cfg.motion_margin * height / prior_unit_height
        pixels, blocks = road_patch(K, normal, height, hw, cfg, ahead)
        if pixels.shape[0] >= cfg.min_pixels:
            centre = math.log(prior_unit_height)
            found = _search(grey_prev, grey_cur, K, R, t, normal, pixels, blocks, cfg,
                            torch.linspace(centre - math.log(cfg.span), centre + math.log(cfg.span),
                                           2 * cfg.steps - 1, dtype=torch.float64))
            if found.unit_height is not None:
                return found
    pixels, blocks = road_patch(K, normal, height, hw, cfg)
    if pixels.shape[0] < cfg.min_pixels:
        return RoadAlignment(None, None, 0, f"road patch of {pixels.shape[0]} px < {cfg.min_pixels}")
    # nothing expected, or not found near the expectation (which may be wrong): the whole plausible range, coarse
    # on every 2nd patch pixel, then fine around the coarse optimum on every pixel
    sub = (pixels[:, 0] % 2 == 0) & (pixels[:, 1] % 2 == 0)
    coarse_h = torch.arange(lo, hi + 1e-9, cfg.coarse_step, dtype=torch.float64)
    coarse = _cost_profiles(grey_prev, grey_cur, K, R, t, normal, pixels[sub], blocks[sub], coarse_h)
    good = torch.isfinite(coarse).all(1) & (torch.nan_to_num(coarse, nan=float("inf")).min(1).values
                                            <= cfg.block_max_cost)
    if int(good.sum()) < cfg.min_blocks:
        return RoadAlignment(None, None, int(good.sum()), f"{int(good.sum())} road blocks align (< {cfg.min_blocks})")
    centre, _, _ = _parabola_min(coarse[good].mean(0), coarse_h)
    return _search(grey_prev, grey_cur, K, R, t, normal, pixels, blocks, cfg,
                   centre + torch.linspace(-2 * cfg.coarse_step, 2 * cfg.coarse_step, cfg.steps,
                                           dtype=torch.float64))


def _search(grey_prev: torch.Tensor, grey_cur: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
            normal: torch.Tensor, pixels: torch.Tensor, blocks: torch.Tensor, cfg: RoadAlignmentConfig,
            log_heights: torch.Tensor) -> RoadAlignment:
    """The best of the sampled ``log_heights`` (parabola-refined) over the blocks that align; None at the edge of
    the range, with a poor cost, or too few blocks."""
    costs = _cost_profiles(grey_prev, grey_cur, K, R, t, normal, pixels, blocks, log_heights)
    good = torch.isfinite(costs).all(1) & (torch.nan_to_num(costs, nan=float("inf")).min(1).values
                                           <= cfg.block_max_cost)
    if int(good.sum()) < cfg.min_blocks:
        return RoadAlignment(None, None, int(good.sum()), f"{int(good.sum())} road blocks align (< {cfg.min_blocks})")
    log_best, cost, edge = _parabola_min(costs[good].mean(0), log_heights)
    if edge:
        return RoadAlignment(None, cost, int(good.sum()), "road alignment at the edge of its search range")
    if cost > cfg.max_cost:
        return RoadAlignment(None, cost, int(good.sum()), f"road alignment cost {cost:.3f} > {cfg.max_cost}")
    return RoadAlignment(math.exp(log_best), cost, int(good.sum()))
