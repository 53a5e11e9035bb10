"""Coarse-to-fine sparse refinement of a network's flow: pyramidal inverse-compositional Lucas–Kanade at the pixels
correspondence selection can use, forward at the candidates and backward at their targets.

Why: DF-VO keeps only correspondences whose forward and backward flows agree to 0.1 px. A network a few pixels off
everywhere gives none; a single-level photometric refinement (:mod:`dfvo.matching.flow_refinement`) only pulls in
errors within about its window (~2 px). Here each candidate's flow starts from the network's and is refined on an
image pyramid (level ``l`` is ``2**l`` smaller), so errors of up to about ``window/2 * 2**(levels-1)`` pixels are
recovered, and only where selection can use the result, so the cost is per candidate, not per pixel.

Steps, for each pair (k, k+1) of consecutive frames (each frame's pyramid built once):
    1. Candidates on frame k: in every region of a ``grid`` (the selection's regions), the ``per_region`` pixels of
       largest Shi–Tomasi score (smaller eigenvalue of the ``window`` x ``window`` mean structure tensor of the
       smoothed grey image), one per ``cell`` x ``cell`` block (its best pixel; spreads them out), score above
       ``min_eigenvalue``.
    2. Forward: each candidate x's flow u, from the network's flow at x, is refined level by level, coarse to fine:
       the template is frame k's ``window`` x ``window`` patch around x at that level (bilinear), the target frame
       k+1's patch around x + u; ``iterations`` Gauss–Newton steps of the inverse-compositional update on the
       zero-mean patches (a brightness offset between the frames is ignored): ``u <- u - H^-1 sum J (W - T)``,
       ``J`` the template's zero-mean gradient, ``H = sum J J^T``; steps clamped to ``max_step`` level pixels.
    3. Backward: at each refined target y = x + u (sub-pixel), the backward flow v (from the network's backward flow
       at y, or ``-u`` with ``backward_init="forward"``) is refined the same way with frame k+1's patch around y as
       the template and frame k as the target.
    4. Written back into the dense fields: the forward flow at x, and the backward flow at the four pixels around
       y (so the bilinear forward-backward test of :mod:`dfvo.matching.consistency` reads exactly v at y). Points
       whose refinement left the image, met a flat patch, or ended with a zero-mean RMS residual above
       ``max_residual`` are not written: there the network's flow stays (and fails the 0.1 px test in general).
       Every other pixel keeps the network's flow.

Sampling: a patch at a sub-pixel position shares one fractional offset, so it is the bilinear blend (4 weights) of
an integer ``(window+1)^2`` patch gathered from the (edge-padded) level image: no ``grid_sample``.

Convention:
    Images (B+1,3,H,W) or (B+1,1,H,W) float in [0,1], consecutive frames; flows (B,2,H,W) in pixels,
    ``flow_fwd[k]`` k->k+1 on frame k's pixels, ``flow_bwd[k]`` k+1->k on frame k+1's pixels (pixel centres at
    integer coordinates, as :mod:`dfvo.matching.flow_warp`). Pyramid level ``l`` pixel ``p_l`` sits at
    ``p_0 = 2**l * p_l + (2**l - 1) / 2`` (2x2 block means). Computation in float32 on the inputs' device; the
    results have the flows' dtype. Sparse points: (P,N,2) (u, v) with a (P,N) bool mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.matching.image_ops import gradient, smaller_eigenvalue, smooth, window_structure_tensor
from dfvo.matching.image_ops import grey as to_grey
from dfvo.validation import choice

__all__ = ["BackwardInit", "CandidatePick", "PyramidRefinementConfig", "build_pyramid", "select_candidates",
           "lucas_kanade", "refine_pyramid", "refine_pairs_pyramid"]


class BackwardInit(StrEnum):
    """Start of the backward refinement: the ``network``'s backward flow at the target, or minus the refined
    ``forward`` flow."""

    network = "network"
    forward = "forward"


class CandidatePick(StrEnum):
    """Which pixel of each cell is a candidate: ``corner`` (the largest Shi–Tomasi score) or ``grid`` (the centre)."""

    corner = "corner"
    grid = "grid"


@dataclass
class PyramidRefinementConfig:
    """Settings of :func:`refine_pyramid` (see the module docstring).

    Attributes:
        levels: pyramid levels (1: the working size only).
        window: patch side at every level (odd).
        iterations: Gauss–Newton iterations per level, coarsest first (one count per level).
        per_region: candidates per region of ``grid``. grid: (rows, cols) of regions.
        cell: candidates are at most one per ``cell`` x ``cell`` block.
        sigma: Gaussian smoothing of the grey working-size image (pixels; 0: none).
        min_eigenvalue: smallest accepted Shi–Tomasi score (intensities in [0,1], gradients per pixel).
        max_step: largest update of a flow component in one iteration, pixels of the level.
        max_residual: largest final zero-mean RMS residual (intensity) of a written point.
        backward_init: ``network`` (the network's backward flow at the target) or ``forward`` (minus the refined
            forward flow).
        candidates: ``corner`` (each cell's pixel of largest score) or ``grid`` (each cell's centre pixel).
        backward_iterations: iterations per level of the backward refinement, coarsest first (None: as
            ``iterations``; levels with 0 are skipped, e.g. ``[0, 0, 2]`` after ``backward_init="forward"``).

    Only lists, strings and numbers, so the class is a valid Hydra/OmegaConf structured config (e.g. a
    ``flow.refine.pyramid`` node).
    """

    levels: int = 3
    window: int = 7
    iterations: list[int] = field(default_factory=lambda: [4, 3, 2])
    per_region: int = 30
    grid: list[int] = field(default_factory=lambda: [10, 10])
    cell: int = 4
    sigma: float = 1.0
    min_eigenvalue: float = 1e-5
    max_step: float = 2.0
    max_residual: float = 0.05
    backward_init: BackwardInit = BackwardInit.network
    backward_iterations: list[int] | None = None
    candidates: CandidatePick = CandidatePick.corner

    def __post_init__(self) -> None:
        its = list(self.iterations)
        b_its = its if self.backward_iterations is None else list(self.backward_iterations)
        checks = [(int(self.levels) >= 1, f"levels={self.levels}; expected >= 1"),
                  (int(self.window) >= 3 and int(self.window) % 2 == 1, f"window={self.window}; expected odd >= 3"),
                  (len(its) == int(self.levels) and all(int(i) >= 0 for i in its),
                   f"iterations={self.iterations}; expected one count >= 0 per level ({self.levels})"),
                  (len(b_its) == int(self.levels) and all(int(i) >= 0 for i in b_its),
                   f"backward_iterations={self.backward_iterations}; expected one count >= 0 per level "
                   f"({self.levels})"),
                  (int(self.per_region) >= 1 and int(self.cell) >= 1, f"per_region={self.per_region}, cell="
                   f"{self.cell}; expected >= 1"),
                  (len(self.grid) == 2 and min(self.grid) >= 1, f"grid={self.grid}; expected [rows, cols] >= 1"),
                  (self.sigma >= 0 and self.min_eigenvalue >= 0 and self.max_step > 0 and self.max_residual > 0,
                   "sigma, min_eigenvalue >= 0 and max_step, max_residual > 0 expected")]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"flow.refine (pyramid): {msg}")
        self.candidates = choice(CandidatePick, self.candidates, "flow.refine.pyramid.candidates")
        self.backward_init = choice(BackwardInit, self.backward_init, "flow.refine.pyramid.backward_init")
        self.iterations = [int(i) for i in its]
        # None stays None (: as ``iterations``), so that overriding ``levels`` and ``iterations`` alone is enough
        self.backward_iterations = None if self.backward_iterations is None else [int(i) for i in b_its]


# ---------------------------------------------------------------------------------------------------- images
def build_pyramid(images: torch.Tensor, levels: int, sigma: float = 1.0) -> list[torch.Tensor]:
    """Grey image and gradients of each level, finest first: ``levels`` tensors (N,3,H_l,W_l) (grey, d/du, d/dv);
    level l+1 is the 2x2 block mean of level l (see the module docstring for the coordinates)."""
    KORNIA_CHECK_SHAPE(images, ["N", "C", "H", "W"])
    g = smooth(to_grey(images), sigma)
    out = []
    for lev in range(levels):
        if lev > 0:
            KORNIA_CHECK(min(g.shape[-2:]) >= 4, f"build_pyramid: level {lev} of a {tuple(images.shape[-2:])} image "
                                                 "is smaller than 4 pixels; use fewer levels")
            g = F.avg_pool2d(g, 2, ceil_mode=True)
        out.append(torch.cat([g, gradient(g)], 1))
    return out


def select_candidates(level0: torch.Tensor, cfg: PyramidRefinementConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate pixels of each frame: (N,M,2) integer (u, v) positions and (N,M) mask, M = regions * per_region.

    Args:
        level0: (N,3,H,W) the finest level of :func:`build_pyramid`.
    """
    N, _, H, W = level0.shape
    gx, gy = level0[:, 1:2], level0[:, 2:3]
    w = int(cfg.window)
    score = smaller_eigenvalue(*window_structure_tensor(gx, gy, w))  # (N,1,H,W)
    r = w // 2 + 1  # keep patches off the border
    score[..., :r, :], score[..., H - r:, :], score[..., :, :r], score[..., :, W - r:] = -1, -1, -1, -1
    c = int(cfg.cell)
    if cfg.candidates == CandidatePick.corner:  # each cell's best pixel
        best, where = F.max_pool2d(score, c, c, ceil_mode=True, return_indices=True)  # (N,1,h,w) per cell
    else:  # each cell's centre pixel
        vv, uu = torch.meshgrid(torch.arange(c // 2, H, c, device=score.device),
                                torch.arange(c // 2, W, c, device=score.device), indexing="ij")
        best = score[..., vv, uu]
        where = (vv * W + uu).expand_as(best)
    hc, wc = best.shape[-2:]
    vc = torch.arange(hc, device=score.device).view(hc, 1).expand(hc, wc) * c  # cell corner rows
    uc = torch.arange(wc, device=score.device).view(1, wc).expand(hc, wc) * c
    gh, gw = int(cfg.grid[0]), int(cfg.grid[1])
    region = ((vc * gh) // H) * gw + (uc * gw) // W  # (hc,wc) region of each cell (by its corner)
    R = gh * gw
    order = torch.argsort(region.reshape(-1), stable=True)
    counts = torch.bincount(region.reshape(-1), minlength=R)
    P = int(counts.max())
    slot = torch.arange(order.numel(), device=score.device) - torch.repeat_interleave(
        torch.cumsum(counts, 0) - counts, counts)
    table = torch.full((R, P), -1, dtype=torch.long, device=score.device)
    table[region.reshape(-1)[order], slot] = order  # cells of each region, padded with -1
    vals = best.reshape(N, -1)
    per = torch.where(table[None] >= 0, vals[:, table.clamp_min(0)], torch.full_like(vals[:, :1, None], -1.0))
    k = min(int(cfg.per_region), P)
    top, pos = torch.topk(per, k, dim=2)  # (N,R,k)
    cells = torch.gather(table[None].expand(N, -1, -1), 2, pos).reshape(N, -1).clamp_min(0)
    flat = torch.gather(where.reshape(N, -1), 1, cells)  # flat pixel index of each chosen cell's best pixel
    mask = top.reshape(N, -1) > float(cfg.min_eigenvalue)
    pts = torch.stack([flat % W, torch.div(flat, W, rounding_mode="floor")], -1).to(torch.float32)
    return pts, mask


# ---------------------------------------------------------------------------------------------------- sampling
class _Sampler:
    """Patches of frames of one pyramid level (edge-padded, flat gather): integer ``(window+1)^2`` patches and
    their bilinear ``window`` x ``window`` blends."""

    def __init__(self, level: torch.Tensor, window: int) -> None:
        self.r = window // 2
        self.pad = self.r + 2
        x = F.pad(level, (self.pad,) * 4, mode="replicate")
        self.N, self.C, self.Hp, self.Wp = x.shape
        self.H, self.W = level.shape[-2:]
        self.flat = x.reshape(self.N, self.C, -1)
        a = torch.arange(window + 1, device=level.device)
        self.offsets = (a.view(-1, 1) * self.Wp + a.view(1, -1)).reshape(-1)  # ((w+1)^2,)
        self.w = window

    def raw(self, frame: torch.Tensor, pos: torch.Tensor, channels: slice) -> tuple[torch.Tensor, torch.Tensor]:
        """Integer patches (P,C',w+1,w+1,N) whose top-left is ``floor(pos) - r``, and the fractions (P,N,2), for
        frames ``frame`` (P,) at ``pos`` (P,N,2) level pixels (clamped to one pixel outside the image). The points
        are the last (contiguous) dimension, so the blends below run on contiguous rows of N values."""
        P, Np, _ = pos.shape
        lo = torch.tensor([-1.0, -1.0], device=pos.device)
        hi = torch.tensor([self.W, self.H], device=pos.device, dtype=torch.float32)
        pos = torch.maximum(torch.minimum(pos, hi), lo)
        base = torch.floor(pos)
        b = base.long() + (self.pad - self.r)
        start = b[..., 1] * self.Wp + b[..., 0]  # (P,N)
        idx = (self.offsets.view(1, -1, 1) + start.unsqueeze(1)).reshape(P, 1, -1)  # (P,1,(w+1)^2*N)
        src = self.flat[frame, channels]  # (P,C',L)
        g = torch.gather(src, 2, idx.expand(-1, src.shape[1], -1))
        return g.view(P, src.shape[1], self.w + 1, self.w + 1, Np), pos - base

    def patch(self, frame: torch.Tensor, pos: torch.Tensor, channels: slice) -> torch.Tensor:
        """Bilinear patches (P,C',w*w,N) around ``pos`` (see :meth:`raw`)."""
        g, f = self.raw(frame, pos, channels)
        P, C, _, _, Np = g.shape
        h = torch.lerp(g[..., :-1, :], g[..., 1:, :], f[..., 0].view(P, 1, 1, 1, Np))  # (P,C,w+1,w,N)
        out = torch.lerp(h[:, :, :-1], h[:, :, 1:], f[..., 1].view(P, 1, 1, 1, Np))  # (P,C,w,w,N)
        return out.reshape(P, C, -1, Np)


def _to_level(p0: torch.Tensor, lev: int) -> torch.Tensor:
    s = 2 ** lev
    return (p0 - 0.5 * (s - 1)) / s


def lucas_kanade(pyramid: list[torch.Tensor], template: torch.Tensor, target: torch.Tensor, pts: torch.Tensor,
                 flow: torch.Tensor, mask: torch.Tensor, cfg: PyramidRefinementConfig,
                 iterations: list[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine the flows of sparse points coarse to fine (inverse-compositional LK on zero-mean patches).

    Each iteration needs ``sum J (W - T)``; ``J`` has zero mean, so the target patch's mean drops out: one gather,
    one bilinear blend and two dot products per point.

    Args:
        pyramid: levels of :func:`build_pyramid` of F frames. template, target: (P,) frame indices of each task.
        pts: (P,N,2) sub-pixel positions (u, v) in the template frame (working-size pixels).
        flow: (P,N,2) initial flows to the target frame. mask: (P,N) bool rows to refine.
        cfg: settings. iterations: per level, coarsest first (default ``cfg.iterations``); levels with 0 iterations
            are skipped.

    Returns:
        ``(flow, ok)``: (P,N,2) refined flows and (P,N) bool: refined, inside the target frame, a well-conditioned
        patch and a final RMS residual within ``max_residual`` (rows not ok hold the initial flow).
    """
    KORNIA_CHECK_SHAPE(pts, ["P", "N", "2"])
    KORNIA_CHECK(flow.shape == pts.shape and mask.shape == pts.shape[:2],
                 f"lucas_kanade: pts {tuple(pts.shape)}, flow {tuple(flow.shape)}, mask {tuple(mask.shape)} differ")
    iterations = list(cfg.iterations if iterations is None else iterations)
    levels = int(cfg.levels)
    samplers = [None if lev > 0 and iterations[levels - 1 - lev] == 0 else _Sampler(pyramid[lev], int(cfg.window))
                for lev in range(levels)]
    # one task at a time: its (n2, N) patch tensors are a quarter of a 4-pair batch's and stay in the CPU's caches
    # (measured 10-15 % faster on one core, more beside a second busy thread); the numbers are the same
    parts = [_lucas_kanade(samplers, template[i:i + 1], target[i:i + 1], pts[i:i + 1], flow[i:i + 1],
                           mask[i:i + 1], cfg, iterations) for i in range(pts.shape[0])]
    if len(parts) == 1:
        return parts[0]
    return torch.cat([q[0] for q in parts]), torch.cat([q[1] for q in parts])


def _lucas_kanade(samplers: list[_Sampler | None], template: torch.Tensor, target: torch.Tensor, pts: torch.Tensor,
                  flow: torch.Tensor, mask: torch.Tensor, cfg: PyramidRefinementConfig, iterations: list[int]
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`lucas_kanade` with each level's sampler built (None: a level without iterations)."""
    n2 = int(cfg.window) ** 2
    pts, u0 = pts.to(torch.float32), flow.to(torch.float32)
    finite = torch.isfinite(u0).all(-1) & torch.isfinite(pts).all(-1) & mask
    u = torch.where(finite.unsqueeze(-1), u0, torch.zeros_like(u0))
    p = torch.where(finite.unsqueeze(-1), pts, torch.zeros_like(pts))
    ok = finite.clone()
    rms = torch.zeros_like(u[..., 0])
    for lev in range(int(cfg.levels) - 1, -1, -1):
        sample = samplers[lev]
        if sample is None:
            continue
        s = float(2 ** lev)
        pl = _to_level(p, lev)
        t = sample.patch(template, pl, slice(0, 3))  # (P,3,n2,N): grey, gx, gy of the template
        tz = t[:, 0] - t[:, 0].mean(1, keepdim=True)  # (P,n2,N)
        J = t[:, 1:] - t[:, 1:].mean(2, keepdim=True)  # (P,2,n2,N)
        Jx, Jy = J[:, 0], J[:, 1]
        a, b, d = (Jx * Jx).sum(1), (Jx * Jy).sum(1), (Jy * Jy).sum(1)  # H = sum J J^T, (P,N)
        det = a * d - b * b
        lam = smaller_eigenvalue(a, b, d)
        good = (lam / n2 > float(cfg.min_eigenvalue) * 0.25 ** lev) & (det > 0)
        inv_det = torch.where(good, 1.0 / torch.where(good, det, 1.0), 0.0)  # 0: the point is not moved
        ia, ib, id_ = d * inv_det, -b * inv_det, a * inv_det  # H^-1
        ok = ok & good if lev == 0 else ok
        Jt = (Jx * tz).sum(1), (Jy * tz).sum(1)  # sum J T
        for _ in range(int(iterations[int(cfg.levels) - 1 - lev])):
            wp = sample.patch(target, pl + u / s, slice(0, 1))[:, 0]  # (P,n2,N)
            jx, jy = (Jx * wp).sum(1) - Jt[0], (Jy * wp).sum(1) - Jt[1]  # sum J (W - T); J has zero mean
            step = torch.stack([ia * jx + ib * jy, ib * jx + id_ * jy], -1)
            u = u - step.clamp(-cfg.max_step, cfg.max_step) * s
        if lev == 0:
            wp = sample.patch(target, pl + u, slice(0, 1))[:, 0]
            rms = (wp - wp.mean(1, keepdim=True) - tz).square().mean(1).sqrt()
    H, W = samplers[0].H, samplers[0].W
    q = p + u
    inside = (q[..., 0] >= 0) & (q[..., 0] <= W - 1) & (q[..., 1] >= 0) & (q[..., 1] <= H - 1)
    ok = ok & inside & (rms <= float(cfg.max_residual)) & torch.isfinite(u).all(-1)
    return torch.where(ok.unsqueeze(-1), u, flow.to(torch.float32)), ok


def _sample_flow(flow: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Bilinear (P,2,H,W) flow at (P,N,2) pixel positions -> (P,N,2) (border-clamped)."""
    H, W = flow.shape[-2:]
    g = torch.stack([2 * pts[..., 0] / max(W - 1, 1) - 1, 2 * pts[..., 1] / max(H - 1, 1) - 1], -1)
    return F.grid_sample(flow, g.unsqueeze(1), mode="bilinear", padding_mode="border",
                         align_corners=True)[:, :, 0].transpose(1, 2)


def _refine(pyramid: list[torch.Tensor], src: torch.Tensor, dst: torch.Tensor, flow_fwd: torch.Tensor,
            flow_bwd: torch.Tensor, cfg: PyramidRefinementConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs (frame ``src[b]`` -> frame ``dst[b]``) of one pyramid: the steps of the module docstring."""
    B, _, H, W = flow_fwd.shape
    pts_all, mask_all = select_candidates(pyramid[0], cfg)
    pts, mask = pts_all[src], mask_all[src]  # (B,M,2) integer pixels of the source frames
    flat = (pts[..., 1] * W + pts[..., 0]).long()  # (B,M)
    fwd = flow_fwd.to(torch.float32).reshape(B, 2, -1)
    u0 = torch.gather(fwd, 2, flat.unsqueeze(1).expand(-1, 2, -1)).transpose(1, 2)
    u, ok_f = lucas_kanade(pyramid, src, dst, pts, u0, mask, cfg)
    y = pts + u
    bwd0 = -u if cfg.backward_init == BackwardInit.forward else _sample_flow(flow_bwd.to(torch.float32), y)
    v, ok_b = lucas_kanade(pyramid, dst, src, y, bwd0, ok_f, cfg, cfg.backward_iterations)
    ok = ok_f & ok_b
    out_f = fwd.clone()
    out_f.scatter_(2, flat.unsqueeze(1).expand(-1, 2, -1), torch.where(ok.unsqueeze(-1), u, u0).transpose(1, 2))
    out_b = flow_bwd.to(torch.float32).reshape(B, 2, -1).clone()
    base = torch.floor(y)
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        cu, cv = base[..., 0] + du, base[..., 1] + dv
        inside = ok & (cu >= 0) & (cu <= W - 1) & (cv >= 0) & (cv <= H - 1)
        idx = torch.where(inside, cv * W + cu, torch.zeros_like(cu)).long()
        cur = torch.gather(out_b, 2, idx.unsqueeze(1).expand(-1, 2, -1)).transpose(1, 2)
        out_b.scatter_(2, idx.unsqueeze(1).expand(-1, 2, -1), torch.where(inside.unsqueeze(-1), v, cur).transpose(1, 2))
    return (out_f.view(B, 2, H, W).to(flow_fwd.dtype), out_b.view(B, 2, H, W).to(flow_bwd.dtype))


def _check(images: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, pairs: int, what: str) -> None:
    KORNIA_CHECK_SHAPE(images, ["N", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(flow_fwd, ["B", "2", "H", "W"])
    KORNIA_CHECK(images.shape[1] in (1, 3), f"{what}: images {tuple(images.shape)}; expected 1 or 3 channels")
    KORNIA_CHECK(flow_fwd.shape[0] == pairs and flow_bwd.shape == flow_fwd.shape
                 and flow_fwd.shape[-2:] == images.shape[-2:],
                 f"{what}: images {tuple(images.shape)} need {pairs} forward and backward flows of their size; got "
                 f"{tuple(flow_fwd.shape)} and {tuple(flow_bwd.shape)}")


def refine_pyramid(images: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor,
                   cfg: PyramidRefinementConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine the flows of the B consecutive pairs (k, k+1) of B+1 frames (each frame's pyramid built once).

    Args:
        images: (B+1,3,H,W) frames in order. flow_fwd: (B,2,H,W) k->k+1 on frame k; flow_bwd: (B,2,H,W) k+1->k
            on frame k+1.
        cfg: settings (defaults: :class:`PyramidRefinementConfig`).

    Returns:
        ``(flow_fwd, flow_bwd)`` (B,2,H,W): refined at the candidates and at their targets (module docstring), the
        inputs elsewhere.
    """
    cfg = cfg or PyramidRefinementConfig()
    B = images.shape[0] - 1
    _check(images, flow_fwd, flow_bwd, B, "refine_pyramid")
    pyramid = build_pyramid(images, int(cfg.levels), float(cfg.sigma))
    k = torch.arange(B, device=flow_fwd.device)
    return _refine(pyramid, k, k + 1, flow_fwd, flow_bwd, cfg)


def refine_pairs_pyramid(images1: torch.Tensor, images2: torch.Tensor, flow_fwd: torch.Tensor,
                         flow_bwd: torch.Tensor, cfg: PyramidRefinementConfig | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`refine_pyramid` for B independent pairs: images1, images2 (B,3,H,W), flows (B,2,H,W) 1->2 and 2->1."""
    cfg = cfg or PyramidRefinementConfig()
    B = images1.shape[0]
    KORNIA_CHECK(images2.shape == images1.shape, f"refine_pairs_pyramid: images1 {tuple(images1.shape)} and images2 "
                                                 f"{tuple(images2.shape)} differ")
    _check(images1, flow_fwd, flow_bwd, B, "refine_pairs_pyramid")
    pyramid = build_pyramid(torch.cat([images1, images2]), int(cfg.levels), float(cfg.sigma))
    k = torch.arange(B, device=flow_fwd.device)
    return _refine(pyramid, k, k + B, flow_fwd, flow_bwd, cfg)
