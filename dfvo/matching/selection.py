"""Correspondence selection from a forward flow and its forward-backward inconsistency.

Convention:
    - ``flow_fwd`` (B,2,H,W): flow i->j in pixels on image i; ``inconsistency`` (B,1,H,W) in pixels on image i
      (``+inf`` = unusable, e.g. the target leaves image j); see :mod:`dfvo.matching.consistency`.
    - Output correspondences are padded to ``num``: ``pts_i`` (B,N,2) are integer pixel centres (u, v) of image
      i, ``pts_j = pts_i + flow_fwd(pts_i)`` (B,N,2) their positions in image j, ``mask`` (B,N) says which rows
      are real. Padded rows hold zeros and ``mask=False``.
    - ``crop_top`` ignores the top ``round(crop_top*H)`` rows (the official code drops the top 30% for depth
      use); the region grid then tiles the remaining rows ``[top, H)``.

Methods:
    - ``local_best_k`` (the paper's reference): the image is split into ``grid`` regions (row/column edges
      ``floor(k*H/gh)``, so sizes differ by at most one pixel when H, W are not divisible); only pixels with
      inconsistency ``< max_inconsistency`` are valid; each region j gives its ``K_j = min(K, Q_j)`` most
      consistent valid pixels, ``K = num // regions`` and Q_j its number of valid pixels (when ``num`` is
      smaller than the number of regions, the ``num`` most consistent region winners).
    - ``best_n``: the ``num`` pixels with the smallest finite inconsistency over the whole (cropped) image.
    - ``uniform``: a regular grid of about ``num`` pixel centres covering the (cropped) image; with a
      ``generator``, ``num`` distinct pixels drawn uniformly at random instead. Rows whose inconsistency is
      not finite are masked out.

Texture (optional, ``texture`` and ``min_texture > 0``, all methods): a pixel whose Shi–Tomasi score in image i
(:func:`dfvo.matching.image_ops.shi_tomasi`) is below ``min_texture`` is unusable whatever its inconsistency: where the
images cannot pin a flow down (flat regions, edges), a smooth network flow can be consistent and wrong alike.

Failure rule (all methods, the official one): with "valid" meaning inconsistency ``< max_inconsistency`` for
``local_best_k`` and finite for the other two, a frame fails when it has fewer than
``min_valid_fraction * num`` valid pixels, or when fewer than ``min_region_fraction`` of the regions contain a
valid pixel. A failed frame keeps whatever was selected (for diagnostics) but ``failed[b]`` is True and
``reasons[b]`` says why; trackers must not use it (constant-motion fallback). With ``relaxed_inconsistency`` a
failed frame is first selected again under each larger bound in turn (``relaxed_bound[b]`` the one that passed).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from functools import lru_cache

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.validation import check, choice, choices

__all__ = ["SelectionMethod", "SelectionConfig", "Correspondences", "select_correspondences"]


class SelectionMethod(StrEnum):
    """Correspondence selection method (see the module docstring)."""

    local_best_k = "local_best_k"
    best_n = "best_n"
    uniform = "uniform"


@dataclass
class SelectionConfig:
    """Forward-backward consistency and correspondence selection (``tracker.correspondence`` of
    :class:`dfvo.tracking.config.TrackerConfig`; the defaults of :func:`select_correspondences`).

    Attributes:
        method: see :class:`SelectionMethod`.
        num_correspondences: correspondences kept per frame pair.
        grid: regions (rows, cols) of ``local_best_k``.
        max_inconsistency: forward-backward inconsistency (pixels) a correspondence may have.
        min_valid_fraction: selection fails (constant motion) below this fraction of consistent pixels.
        min_region_fraction: ``local_best_k`` regions with fewer consistent pixels are skipped.
        crop_top: fraction of image rows at the top not used.
        min_texture: pixels whose Shi–Tomasi score (intensities in [0,1], gradients per pixel, 11x11 window, the
            refinement's) is below this are not used; 0: no texture test (the paper).
        relaxed_inconsistency: a pair that fails the selection rule at ``max_inconsistency`` is selected again at
            each of these larger bounds in turn (pixels, ascending) and tracked from the first that passes, flagged
            in its diagnostics (``selection_max_inconsistency``); the bound doubles from the official 0.1 px up to
            0.8 px by default (measured on the panel: docs/robots.md); empty: it falls back to constant motion (the
            paper).
    """

    method: SelectionMethod = SelectionMethod.local_best_k
    num_correspondences: int = 2000
    grid: list[int] = field(default_factory=lambda: [10, 10])
    max_inconsistency: float = 0.1
    min_valid_fraction: float = 0.1
    min_region_fraction: float = 0.1
    crop_top: float = 0.0
    min_texture: float = 0.0
    relaxed_inconsistency: list[float] = field(default_factory=lambda: [0.2, 0.4, 0.8])

    def __post_init__(self) -> None:
        self.method = choice(SelectionMethod, self.method, "tracker.correspondence.method")
        check(len(self.grid) == 2 and all(int(g) > 0 for g in self.grid),
               f"tracker.correspondence.grid={list(self.grid)}; expected [rows, cols] of positive integers")
        self.grid = [int(g) for g in self.grid]
        check(int(self.num_correspondences) > 0, f"tracker.correspondence.num_correspondences="
                                                 f"{self.num_correspondences}; expected a positive integer")
        check(self.max_inconsistency > 0, f"tracker.correspondence.max_inconsistency={self.max_inconsistency}; "
                                           "expected > 0")
        self.relaxed_inconsistency = [float(v) for v in self.relaxed_inconsistency]
        bounds = [float(self.max_inconsistency), *self.relaxed_inconsistency]
        check(all(a < b for a, b in zip(bounds[:-1], bounds[1:], strict=False)),
              f"tracker.correspondence.relaxed_inconsistency={self.relaxed_inconsistency}; expected ascending bounds "
              f"above max_inconsistency={self.max_inconsistency}")
        check(float(self.min_texture) >= 0, f"tracker.correspondence.min_texture={self.min_texture}; expected >= 0 "
                                            "(0: no texture test)")
        check(0.0 <= self.crop_top < 1.0, f"tracker.correspondence.crop_top={self.crop_top}; expected [0, 1)")


_DEFAULTS = SelectionConfig()


@dataclass
class Correspondences:
    """Padded 2-D/2-D correspondences between image i and image j for B frame pairs.

    Attributes:
        pts_i: (B,N,2) pixel positions (u, v) in image i.
        pts_j: (B,N,2) positions in image j (``pts_i + flow_fwd(pts_i)``).
        mask: (B,N) bool, True for real rows.
        inconsistency: (B,N) forward-backward inconsistency of each row in pixels (0 in padded rows).
        failed: (B,) bool, True when frame b failed the selection rule.
        reasons: per frame, why it failed (None when it did not).
        relaxed_bound: per frame, the relaxed bound (pixels) it was selected under after failing at
            ``max_inconsistency`` (None: selected as usual, or failed at every bound).
    """

    pts_i: torch.Tensor
    pts_j: torch.Tensor
    mask: torch.Tensor
    inconsistency: torch.Tensor
    failed: torch.Tensor
    reasons: list[str | None]
    relaxed_bound: list[float | None] = field(default_factory=list)

    @property
    def num_valid(self) -> torch.Tensor:
        """(B,) number of real rows per frame."""
        return self.mask.sum(dim=1)


def _edges(length: int, parts: int) -> list[int]:
    return [(k * length) // parts for k in range(parts + 1)]


@lru_cache(maxsize=32)
def _region_index(height: int, width: int, top: int, grid: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixel indices of each region, padded with the sentinel ``H*W``.

    Returns:
        index: (R, P) long, P = the largest region size; region r = row block r // gw, column block r % gw.
        region_of_pixel: (H*W,) long region id of each pixel (-1 for cropped rows).
    """
    gh, gw = grid
    rows = _edges(height - top, gh)
    cols = _edges(width, gw)
    region_of_pixel = torch.full((height, width), -1, dtype=torch.long)
    blocks = []
    for a in range(gh):
        for c in range(gw):
            r0, r1 = top + rows[a], top + rows[a + 1]
            c0, c1 = cols[c], cols[c + 1]
            region_of_pixel[r0:r1, c0:c1] = a * gw + c
            vv, uu = torch.meshgrid(torch.arange(r0, r1), torch.arange(c0, c1), indexing="ij")
            blocks.append((vv * width + uu).reshape(-1))
    size = max(max(b.numel() for b in blocks), 1)
    index = torch.full((gh * gw, size), height * width, dtype=torch.long)
    for r, b in enumerate(blocks):
        index[r, : b.numel()] = b
    return index, region_of_pixel.reshape(-1)


def _check_args(method: str, num: int, grid: tuple[int, int], crop_top: float, height: int) -> int:
    KORNIA_CHECK(method in choices(SelectionMethod),
                 f"select_correspondences: method must be one of {choices(SelectionMethod)}, got {method!r}")
    KORNIA_CHECK(num > 0, f"select_correspondences: num must be positive, got {num}")
    KORNIA_CHECK(len(grid) == 2 and grid[0] > 0 and grid[1] > 0,
                 f"select_correspondences: grid must be two positive ints (rows, cols), got {grid}")
    KORNIA_CHECK(0.0 <= crop_top < 1.0, f"select_correspondences: crop_top must be in [0, 1), got {crop_top}")
    top = int(round(crop_top * height))
    KORNIA_CHECK(height - top >= grid[0], f"select_correspondences: {height - top} rows left after crop_top="
                 f"{crop_top} cannot hold a grid of {grid[0]} region rows")
    return top


def _gather_rows(flow_flat: torch.Tensor, incon_flat: torch.Tensor, idx: torch.Tensor, mask: torch.Tensor,
                 width: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel positions, targets and inconsistency of flat indices ``idx`` (B,N); masked rows zeroed."""
    safe = torch.where(mask, idx, torch.zeros_like(idx))
    u = (safe % width).to(flow_flat.dtype)
    v = torch.div(safe, width, rounding_mode="floor").to(flow_flat.dtype)
    pts_i = torch.stack([u, v], dim=-1)
    flow = torch.gather(flow_flat, 2, safe.unsqueeze(1).expand(-1, 2, -1)).transpose(1, 2)
    pts_j = pts_i + flow
    incon = torch.gather(incon_flat, 1, safe)
    zero = torch.zeros((), dtype=flow_flat.dtype, device=flow_flat.device)
    m2 = mask.unsqueeze(-1)
    return torch.where(m2, pts_i, zero), torch.where(m2, pts_j, zero), torch.where(mask, incon, zero)


def _uniform_grid(height: int, width: int, top: int, num: int, device: torch.device) -> torch.Tensor:
    """Flat indices of a regular grid of at most ``num`` pixel centres over rows ``[top, H)``."""
    rows_avail = height - top
    n_cols = max(1, min(width, int(round((num * width / rows_avail) ** 0.5))))
    n_rows = max(1, min(rows_avail, num // n_cols))
    u = torch.floor((torch.arange(n_cols, device=device) + 0.5) * width / n_cols).long()
    v = top + torch.floor((torch.arange(n_rows, device=device) + 0.5) * rows_avail / n_rows).long()
    return (v[:, None] * width + u[None, :]).reshape(-1)


def select_correspondences(
    flow_fwd: torch.Tensor,
    inconsistency: torch.Tensor,
    method: SelectionMethod | str = _DEFAULTS.method,
    num: int = _DEFAULTS.num_correspondences,
    grid: tuple[int, int] = tuple(_DEFAULTS.grid),
    max_inconsistency: float = _DEFAULTS.max_inconsistency,
    min_valid_fraction: float = _DEFAULTS.min_valid_fraction,
    min_region_fraction: float = _DEFAULTS.min_region_fraction,
    crop_top: float = _DEFAULTS.crop_top,
    generator: torch.Generator | None = None,
    texture: torch.Tensor | None = None,
    min_texture: float = _DEFAULTS.min_texture,
    relaxed_inconsistency: Sequence[float] = tuple(_DEFAULTS.relaxed_inconsistency),
) -> Correspondences:
    """Select up to ``num`` correspondences per frame pair from a forward flow.

    Args:
        flow_fwd: (B,2,H,W) flow i->j in pixels on image i.
        inconsistency: (B,1,H,W) forward-backward inconsistency in pixels (``+inf`` = unusable).
        method: ``"local_best_k"``, ``"best_n"`` or ``"uniform"`` (see the module docstring).
        The defaults are :class:`SelectionConfig`'s (``num`` is its ``num_correspondences``).
        num: N, the number of correspondences (the padded output size).
        grid: (rows, cols) of regions for local best-K and for the region-coverage failure test.
        max_inconsistency: validity threshold in pixels for local best-K (strict ``<``).
        min_valid_fraction: a frame fails with fewer than ``min_valid_fraction * num`` valid pixels.
        min_region_fraction: a frame fails when fewer than this fraction of regions hold a valid pixel.
        crop_top: fraction of the top rows to ignore, in [0, 1).
        generator: with ``method="uniform"``, draw random pixels with it instead of a regular grid.
        texture: (B,1,H,W) Shi–Tomasi score of image i; with ``min_texture > 0`` pixels scoring below it are
            unusable (module docstring). Needed when ``min_texture > 0``.
        min_texture: see ``texture``.
        relaxed_inconsistency: ascending bounds (pixels) above ``max_inconsistency``: a frame that fails the rule is
            selected again under each in turn and keeps the first that passes (``relaxed_bound`` says which);
            ``()``: the paper's rule.

    Returns:
        :class:`Correspondences` with (B,N,...) padded rows.
    """
    args = (method, num, grid, min_valid_fraction, min_region_fraction, crop_top, generator, min_texture)
    corr = _select(flow_fwd, inconsistency, max_inconsistency, texture, *args)
    corr.relaxed_bound = [None] * flow_fwd.shape[0]
    for bound in relaxed_inconsistency:
        todo = corr.failed.nonzero()[:, 0]
        if len(todo) == 0:
            break
        retry = _select(flow_fwd[todo], inconsistency[todo], bound, None if texture is None else texture[todo], *args)
        for k, b in enumerate(todo.tolist()):
            if not bool(retry.failed[k]):
                corr.pts_i[b], corr.pts_j[b], corr.mask[b] = retry.pts_i[k], retry.pts_j[k], retry.mask[k]
                corr.inconsistency[b], corr.failed[b], corr.reasons[b] = retry.inconsistency[k], False, None
                corr.relaxed_bound[b] = float(bound)
    return corr


def _select(flow_fwd: torch.Tensor, inconsistency: torch.Tensor, max_inconsistency: float,
            texture: torch.Tensor | None, method: SelectionMethod | str, num: int, grid: tuple[int, int],
            min_valid_fraction: float, min_region_fraction: float, crop_top: float,
            generator: torch.Generator | None, min_texture: float) -> Correspondences:
    """:func:`select_correspondences` under one bound (its arguments, without ``relaxed_inconsistency``)."""
    KORNIA_CHECK_SHAPE(flow_fwd, ["B", "2", "H", "W"])
    KORNIA_CHECK_SHAPE(inconsistency, ["B", "1", "H", "W"])
    KORNIA_CHECK(inconsistency.shape[0] == flow_fwd.shape[0] and inconsistency.shape[-2:] == flow_fwd.shape[-2:],
                 f"select_correspondences: inconsistency {tuple(inconsistency.shape)} must match flow_fwd "
                 f"{tuple(flow_fwd.shape)} in B, H, W")
    B, _, H, W = flow_fwd.shape
    grid = (int(grid[0]), int(grid[1]))
    top = _check_args(method, num, grid, crop_top, H)
    device = flow_fwd.device
    index, region_of_pixel = _region_index(H, W, top, grid)
    index, region_of_pixel = index.to(device), region_of_pixel.to(device)
    R = grid[0] * grid[1]

    incon_flat = inconsistency.reshape(B, H * W)
    incon_flat = torch.where(torch.isnan(incon_flat), torch.full_like(incon_flat, float("inf")), incon_flat)
    if top > 0:
        incon_flat = incon_flat.clone()
        incon_flat[:, : top * W] = float("inf")
    if min_texture > 0:
        KORNIA_CHECK(texture is not None and texture.shape == inconsistency.shape,
                     f"select_correspondences: min_texture={min_texture} needs the (B,1,H,W) texture of image i "
                     f"shaped like the inconsistency {tuple(inconsistency.shape)}; got "
                     f"{None if texture is None else tuple(texture.shape)}")
        flat = texture.reshape(B, H * W).to(incon_flat.device)
        incon_flat = torch.where(flat >= min_texture, incon_flat, float("inf"))
    flow_flat = flow_fwd.reshape(B, 2, H * W)
    finite = torch.isfinite(incon_flat)
    valid = finite & (incon_flat < max_inconsistency) if method == "local_best_k" else finite

    if method == "local_best_k":
        k = max(1, min(num // R, index.shape[1]))
        padded = torch.cat([incon_flat, incon_flat.new_full((B, 1), float("inf"))], dim=1)
        padded = torch.where(torch.cat([valid, valid.new_zeros((B, 1))], 1), padded, float("inf"))
        per_region = padded[:, index]  # (B,R,P)
        best, pos = torch.topk(per_region, k, dim=2, largest=False, sorted=True)  # (B,R,k)
        idx = torch.gather(index.unsqueeze(0).expand(B, -1, -1), 2, pos).reshape(B, R * k)
        sel_mask = torch.isfinite(best).reshape(B, R * k)
        if R * k > num:  # fewer rows than regions (num < R): keep the num most consistent region winners
            keep = torch.topk(best.reshape(B, R * k), num, dim=1, largest=False, sorted=False).indices
            keep = torch.sort(keep, dim=1).values
            idx, sel_mask = torch.gather(idx, 1, keep), torch.gather(sel_mask, 1, keep)
        elif R * k < num:
            pad = num - R * k
            idx = torch.cat([idx, idx.new_zeros((B, pad))], 1)
            sel_mask = torch.cat([sel_mask, sel_mask.new_zeros((B, pad))], 1)
        # compact the real rows to the front, keeping region-major order
        order = torch.sort((~sel_mask).to(torch.uint8), dim=1, stable=True).indices
        idx, sel_mask = torch.gather(idx, 1, order), torch.gather(sel_mask, 1, order)
    elif method == "best_n":
        n = min(num, H * W)
        vals, idx = torch.topk(incon_flat, n, dim=1, largest=False, sorted=True)
        sel_mask = torch.isfinite(vals)
        if n < num:
            idx = torch.cat([idx, idx.new_zeros((B, num - n))], 1)
            sel_mask = torch.cat([sel_mask, sel_mask.new_zeros((B, num - n))], 1)
    else:
        if generator is None:
            cells = _uniform_grid(H, W, top, num, device).unsqueeze(0).expand(B, -1)
        else:
            n = min(num, (H - top) * W)
            gen_device = generator.device
            keys = torch.rand((B, (H - top) * W), generator=generator, device=gen_device).to(device)
            cells = torch.topk(keys, n, dim=1).indices + top * W
        n = cells.shape[1]
        idx = torch.cat([cells, cells.new_zeros((B, num - n))], 1)
        sel_mask = torch.cat([torch.gather(finite, 1, cells), finite.new_zeros((B, num - n))], 1)

    pts_i, pts_j, incon = _gather_rows(flow_flat, incon_flat, idx, sel_mask, W)
    failed, reasons = _failure(valid, region_of_pixel, R, num, max_inconsistency, min_valid_fraction,
                               min_region_fraction, method, min_texture)
    return Correspondences(pts_i, pts_j, sel_mask, incon, failed, reasons)


def _failure(valid: torch.Tensor, region_of_pixel: torch.Tensor, R: int, num: int, max_inconsistency: float,
             min_valid_fraction: float, min_region_fraction: float, method: str,
             min_texture: float = 0.0) -> tuple[torch.Tensor, list]:
    """Apply the official failure rule; returns (B,) failed and the per-frame reasons."""
    B = valid.shape[0]
    n_valid = valid.sum(dim=1)
    in_grid = region_of_pixel >= 0
    hits = torch.zeros((B, R), dtype=torch.long, device=valid.device)
    hits.scatter_add_(1, region_of_pixel.clamp_min(0).unsqueeze(0).expand(B, -1), (valid & in_grid).long())
    regions_hit = (hits > 0).sum(dim=1)
    need_valid = min_valid_fraction * num
    need_regions = min_region_fraction * R
    few_valid = n_valid.to(torch.float64) < need_valid
    few_regions = regions_hit.to(torch.float64) < need_regions
    failed = few_valid | few_regions
    what = f"inconsistency < {max_inconsistency} px" if method == "local_best_k" else "a flow target in the image"
    if min_texture > 0:
        what += f" and texture >= {min_texture:g}"
    reasons: list[str | None] = []
    for b in range(B):
        parts = []
        if bool(few_valid[b]):
            parts.append(f"only {int(n_valid[b])} pixels with {what} (need >= {need_valid:g})")
        if bool(few_regions[b]):
            parts.append(f"valid pixels in only {int(regions_hit[b])} of {R} regions (need >= {need_regions:g})")
        reasons.append("; ".join(parts) if parts else None)
    return failed, reasons
