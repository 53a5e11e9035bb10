"""Two-view geometry on padded, batched correspondences: essential and homography RANSAC, decomposition
with cheirality, triangulation, Sampson residuals.

Convention:
    ``pts_i`` (B,N,2) are pixels in image i (the previous frame), ``pts_j`` (B,N,2) the matching pixels in
    image j (the current frame); ``mask`` (B,N) bool marks the real rows of the padding. ``K`` (B,3,3) are
    the intrinsics (same camera for both images). The essential matrix satisfies ``x_j^T E x_i = 0`` on
    normalised coordinates ``x = K^-1 [u, v, 1]^T``, and its decomposition ``(R, t)`` is ``T_j_i``: it maps
    frame-i points into camera j (``t`` has unit norm). Invert it to get ``T_prev_cur``.

Randomness: each frame of the batch draws from its own ``torch.Generator`` (a list, one per frame), so a
frame's result does not depend on which other frames share its batch (batched == unbatched).

Everything runs in float64 internally (the five-point solver of kornia is float64 anyway).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.geometry.epipolar import decompose_essential_matrix, find_essential, triangulate_points
from kornia.geometry.homography import find_homography_dlt

__all__ = ["TwoViewResult", "normalise_points", "sampson_sq", "homography_error_sq", "find_essential_ransac",
           "find_homography_ransac", "decompose_essential", "triangulate", "ray_depths", "frame_rand"]


@dataclass
class TwoViewResult:
    """Result of :func:`find_essential_ransac` / :func:`find_homography_ransac`.

    Attributes:
        model: (B,3,3) essential matrix (normalised coordinates) or homography (pixels, ``x_j ~ H x_i``).
        inliers: (B,N) bool rows within the threshold of ``model``.
        num_inliers: (B,) long.
        success: (B,) bool, a model was found from enough rows.
    """

    model: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    success: torch.Tensor


def _check(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, K: torch.Tensor | None, name: str) -> None:
    KORNIA_CHECK_SHAPE(pts_i, ["B", "N", "2"])
    KORNIA_CHECK_SHAPE(pts_j, ["B", "N", "2"])
    KORNIA_CHECK_SHAPE(mask, ["B", "N"])
    ok = pts_j.shape == pts_i.shape and mask.shape == pts_i.shape[:2]
    if K is not None:
        KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
        ok = ok and K.shape[0] == pts_i.shape[0]
    KORNIA_CHECK(ok, f"{name}: pts_i {tuple(pts_i.shape)}, pts_j {tuple(pts_j.shape)}, mask {tuple(mask.shape)}"
                     f"{'' if K is None else f', K {tuple(K.shape)}'} must share (B,N)")


def frame_rand(generators: list[torch.Generator] | None, batch: int, shape: tuple[int, ...],
               device: torch.device) -> torch.Tensor:
    """(B,*shape) uniform float64 numbers, frame b drawn from ``generators[b]`` (on the generator's device)."""
    if generators is None:
        return torch.rand((batch, *shape), dtype=torch.float64, device=device)
    KORNIA_CHECK(len(generators) == batch, f"frame_rand: {len(generators)} generators for a batch of {batch}")
    return torch.stack([torch.rand(shape, generator=g, dtype=torch.float64, device=g.device).to(device)
                        for g in generators])


def _sample_rows(mask: torch.Tensor, num_samples: int, size: int,
                 generators: list[torch.Generator] | None) -> torch.Tensor:
    """(B,S,size) long: per sample, ``size`` distinct rows among the valid rows of each frame."""
    B, N = mask.shape
    u = frame_rand(generators, B, (num_samples, N), mask.device)
    u = torch.where(mask[:, None, :], u, torch.full_like(u, -1.0))
    return u.topk(size, dim=-1).indices


def normalise_points(pts: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(B,N,2) pixels -> (B,N,2) normalised camera coordinates ``K^-1 [u, v, 1]``."""
    Kd = K.to(pts.dtype)
    x = (pts[..., 0] - Kd[:, None, 0, 2] - Kd[:, None, 0, 1] * (pts[..., 1] - Kd[:, None, 1, 2]) / Kd[:, None, 1, 1])
    return torch.stack([x / Kd[:, None, 0, 0], (pts[..., 1] - Kd[:, None, 1, 2]) / Kd[:, None, 1, 1]], -1)


def sampson_sq(F: torch.Tensor, x_i: torch.Tensor, x_j: torch.Tensor) -> torch.Tensor:
    """Squared Sampson distance of (B,N,2) points to (B,M,3,3) epipolar matrices -> (B,M,N).

    With ``F = K^-T E K^-1`` and pixel coordinates this is the squared Sampson distance in pixels (GRIC's
    residual for E); with ``E`` and normalised coordinates it is the normalised one (RANSAC's test).
    """
    B, M = F.shape[:2]
    N = x_i.shape[1]
    hi = torch.cat([x_i, torch.ones_like(x_i[..., :1])], -1).transpose(1, 2)  # (B,3,N)
    hj = torch.cat([x_j, torch.ones_like(x_j[..., :1])], -1).transpose(1, 2)
    Fx = (F.reshape(B, M * 3, 3) @ hi).view(B, M, 3, N)  # F x_i, one GEMM per frame
    Ftx = (F.transpose(-1, -2).reshape(B, M * 3, 3) @ hj).view(B, M, 3, N)  # F^T x_j
    num = (Ftx[:, :, 0] * x_i[:, None, :, 0] + Ftx[:, :, 1] * x_i[:, None, :, 1] + Ftx[:, :, 2]) ** 2
    den = Fx[:, :, 0] ** 2 + Fx[:, :, 1] ** 2 + Ftx[:, :, 0] ** 2 + Ftx[:, :, 1] ** 2
    return num / den.clamp_min(1e-30)


def homography_error_sq(H: torch.Tensor, x_i: torch.Tensor, x_j: torch.Tensor) -> torch.Tensor:
    """Torr's first-order geometric transfer error (squared, pixels) of (B,N,2) pairs under (B,M,3,3) H -> (B,M,N).

    The two algebraic residuals ``e`` of ``x_j x (H x_i) = 0`` are weighted by ``(J J^T)^-1`` with ``J`` their
    Jacobian with respect to both points: the Sampson approximation of the reprojection error in both images.
    """
    u1, v1 = x_i[:, None, :, 0], x_i[:, None, :, 1]
    u2, v2 = x_j[:, None, :, 0], x_j[:, None, :, 1]
    h = [H[:, :, r, None, 0] * u1 + H[:, :, r, None, 1] * v1 + H[:, :, r, None, 2] for r in range(3)]
    e1 = v2 * h[2] - h[1]
    e2 = h[0] - u2 * h[2]
    Hm = [[H[:, :, r, c, None] for c in range(3)] for r in range(3)]
    # J rows: d e / d (u1, v1, u2, v2)
    a = (v2 * Hm[2][0] - Hm[1][0], v2 * Hm[2][1] - Hm[1][1], torch.zeros_like(u2), h[2])
    b = (Hm[0][0] - u2 * Hm[2][0], Hm[0][1] - u2 * Hm[2][1], -h[2], torch.zeros_like(u2))
    s11 = sum(x * x for x in a)
    s22 = sum(x * x for x in b)
    s12 = sum(x * y for x, y in zip(a, b, strict=True))
    det = (s11 * s22 - s12 * s12).clamp_min(1e-30)
    return (s22 * e1 * e1 - 2 * s12 * e1 * e2 + s11 * e2 * e2) / det


def _best_candidates(err: torch.Tensor, thr_sq: float, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """err (B,M,N) -> (inlier counts (B,M), MSAC-style tie-break score (B,M)); NaN models score worst."""
    valid = mask[:, None, :] & torch.isfinite(err)
    inl = valid & (err < thr_sq)
    count = inl.sum(-1)
    trunc = torch.where(valid, err.clamp(max=thr_sq), torch.full_like(err, thr_sq)).sum(-1)
    return count, trunc


def _pick(models: torch.Tensor, err: torch.Tensor, thr_sq: float, mask: torch.Tensor,
          groups: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per group of candidates (B, groups*M) choose most inliers (then lowest truncated error).

    Returns chosen models (B,groups,3,3) and their inliers (B,groups,N).
    """
    B, GM, N = err.shape
    count, trunc = _best_candidates(err, thr_sq, mask)
    key = count.to(torch.float64) * 1e6 - trunc / max(thr_sq, 1e-30) / (N + 1) * 1e-3
    key = key.view(B, groups, GM // groups)
    best = key.argmax(-1)  # (B,groups)
    flat = best + torch.arange(groups, device=err.device)[None] * (GM // groups)
    chosen = models.gather(1, flat[..., None, None].expand(B, groups, 3, 3))
    e = err.gather(1, flat[..., None].expand(B, groups, N))
    return chosen, mask[:, None] & torch.isfinite(e) & (e < thr_sq)


def _finalise(models: torch.Tensor, inl: torch.Tensor, min_inliers: int) -> TwoViewResult:
    """Across repeats (B,R,...) keep the one with most inliers."""
    counts = inl.sum(-1)
    best = counts.argmax(-1)
    B = models.shape[0]
    ar = torch.arange(B, device=models.device)
    model, inliers = models[ar, best], inl[ar, best]
    num = inliers.sum(-1)
    return TwoViewResult(model, inliers, num, num >= min_inliers)


def find_essential_ransac(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, K: torch.Tensor,
                          threshold_px: float = 0.2, iterations: int = 20, repeats: int = 5,
                          generators: list[torch.Generator] | None = None, refine: bool = True,
                          preview: int = 256, max_real: int = 6) -> TwoViewResult:
    """Essential matrix by batched five-point RANSAC (kornia ``find_essential``), repeated ``repeats`` times.

    Each repeat draws ``iterations`` minimal samples (equivalent to running on freshly shuffled rows), keeps
    its best candidate (most inliers, ties by truncated error) and, when ``refine``, refits on its inliers with
    the least-squares five-point solver (local optimisation); the repeat with most inliers wins.
    The pixel threshold is converted to normalised coordinates by the mean focal length: a row is an inlier
    when its normalised Sampson distance is below ``threshold_px / f``.

    Args:
        pts_i, pts_j: (B,N,2) pixels in images i and j.
        mask: (B,N) bool valid rows.
        K: (B,3,3) intrinsics.
        threshold_px: inlier threshold in pixels (official 0.2).
        iterations: minimal samples per repeat.
        repeats: independent repeats, most inliers wins (official 5).
        generators: one ``torch.Generator`` per frame for reproducible sampling (None: global RNG).
        refine: least-squares refit of each repeat's winner on its inliers.
        preview: rows (random, per frame) on which all candidates are ranked (float32) before the full
            float64 scoring of each repeat's winner.
        max_real: real five-point candidates kept per sample (of kornia's ten slots).

    Returns:
        :class:`TwoViewResult` with ``model`` = E (B,3,3) float64; ``success`` False with fewer than 5 rows.
    """
    _check(pts_i, pts_j, mask, K, "find_essential_ransac")
    KORNIA_CHECK(threshold_px > 0 and iterations > 0 and repeats > 0,
                 f"find_essential_ransac: need threshold_px, iterations, repeats > 0; got {threshold_px}, "
                 f"{iterations}, {repeats}")
    B, N = mask.shape
    Kd = K.to(torch.float64)
    xi, xj = normalise_points(pts_i.to(torch.float64), Kd), normalise_points(pts_j.to(torch.float64), Kd)
    f = 0.5 * (Kd[:, 0, 0] + Kd[:, 1, 1])
    # a single threshold per batch keeps the code simple; frames of one sequence share K
    thr = float((threshold_px / f).max())
    thr_sq = thr * thr
    enough = mask.sum(-1) >= 5
    m = mask & enough[:, None]
    if N < 5 or not bool(enough.any()):
        eye = torch.zeros(B, 3, 3, dtype=torch.float64, device=pts_i.device)
        z = torch.zeros_like(mask)
        return TwoViewResult(eye, z, z.sum(-1), torch.zeros_like(enough))
    S = iterations * repeats
    idx = _sample_rows(torch.where(enough[:, None], mask, torch.ones_like(mask)), S, 5, generators)  # (B,S,5)
    si = xi.gather(1, idx.view(B, S * 5, 1).expand(-1, -1, 2)).view(B * S, 5, 2)
    sj = xj.gather(1, idx.view(B, S * 5, 1).expand(-1, -1, 2)).view(B * S, 5, 2)
    cand = find_essential(si, sj).view(B, S, 10, 3, 3)
    # complex roots come back as NaN slots: keep the first ``max_real`` real candidates of each sample
    # (five-point samples rarely have more than six real solutions), which cuts the scoring work
    finite = torch.isfinite(cand).all(-1).all(-1)
    order = torch.sort((~finite).to(torch.uint8), dim=-1, stable=True).indices[..., :max_real]
    cand = cand.gather(2, order[..., None, None].expand(-1, -1, -1, 3, 3)).view(B, S * max_real, 3, 3)
    # preemptive scoring: rank the candidates on a random subset of rows, then score each repeat's winner
    # on all rows (keeps the cost linear in candidates + rows instead of their product)
    sub = _sample_rows(torch.where(enough[:, None], mask, torch.ones_like(mask)), 1, min(N, preview),
                       generators)[:, 0]
    sub_m = m.gather(1, sub)
    sub2 = sub[..., None].expand(-1, -1, 2)
    err_sub = sampson_sq(cand.float(), xi.gather(1, sub2).float(), xj.gather(1, sub2).float()).double()
    models, _ = _pick(cand, err_sub, thr_sq, sub_m, repeats)  # (B,R,3,3)
    models, inl = _pick(models, sampson_sq(models, xi, xj), thr_sq, m, repeats)  # (B,R,N)
    if refine:
        w = inl.to(torch.float64).view(B * repeats, N)
        ok = w.sum(-1) >= 6
        if bool(ok.any()):
            ref = find_essential(xi.repeat_interleave(repeats, 0), xj.repeat_interleave(repeats, 0),
                                 w).view(B, repeats * 10, 3, 3)
            allc = torch.cat([models[:, :, None], ref.view(B, repeats, 10, 3, 3)], 2).view(B, repeats * 11, 3, 3)
            err = sampson_sq(allc, xi, xj)
            models, inl = _pick(allc, err, thr_sq, m, repeats)
    res = _finalise(models, inl, 5)
    res.success &= enough
    return res


def find_homography_ransac(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, threshold_px: float = 1.0,
                           iterations: int = 50, repeats: int = 1,
                           generators: list[torch.Generator] | None = None, preview: int = 256) -> TwoViewResult:
    """Homography ``x_j ~ H x_i`` by batched four-point DLT RANSAC (kornia ``find_homography_dlt``) with a
    weighted DLT refit on the winner's inliers. Inliers: Torr's geometric error (:func:`homography_error_sq`)
    below ``threshold_px`` pixels.

    Args:
        pts_i, pts_j: (B,N,2) pixels. mask: (B,N) bool. threshold_px: pixels (official 1).
        iterations, repeats: samples per repeat and repeats (most inliers wins).
        generators: one generator per frame (None: global RNG).
        preview: rows (random, per frame) on which all candidates are ranked before the full scoring.

    Returns:
        :class:`TwoViewResult` with ``model`` = H (B,3,3) float64.
    """
    _check(pts_i, pts_j, mask, None, "find_homography_ransac")
    B, N = mask.shape
    xi, xj = pts_i.to(torch.float64), pts_j.to(torch.float64)
    thr_sq = float(threshold_px) ** 2
    enough = mask.sum(-1) >= 4
    if N < 4 or not bool(enough.any()):
        z = torch.zeros_like(mask)
        return TwoViewResult(torch.eye(3, dtype=torch.float64).repeat(B, 1, 1), z, z.sum(-1), torch.zeros_like(enough))
    S = iterations * repeats
    idx = _sample_rows(torch.where(enough[:, None], mask, torch.ones_like(mask)), S, 4, generators)
    si = xi.gather(1, idx.view(B, S * 4, 1).expand(-1, -1, 2)).view(B * S, 4, 2)
    sj = xj.gather(1, idx.view(B, S * 4, 1).expand(-1, -1, 2)).view(B * S, 4, 2)
    cand = find_homography_dlt(si, sj).view(B, S, 3, 3)
    m = mask & enough[:, None]
    sub = _sample_rows(torch.where(enough[:, None], mask, torch.ones_like(mask)), 1, min(N, preview),
                       generators)[:, 0]
    sub2 = sub[..., None].expand(-1, -1, 2)
    err_sub = homography_error_sq(cand, xi.gather(1, sub2), xj.gather(1, sub2))
    models, _ = _pick(cand, err_sub, thr_sq, m.gather(1, sub), repeats)
    models, inl = _pick(models, homography_error_sq(models, xi, xj), thr_sq, m, repeats)
    w = inl.to(torch.float64).view(B * repeats, N)
    ref = find_homography_dlt(xi.repeat_interleave(repeats, 0), xj.repeat_interleave(repeats, 0), w)
    ref = torch.where((w.sum(-1) >= 4)[:, None, None] & torch.isfinite(ref).all(-1).all(-1)[:, None, None],
                      ref, models.view(B * repeats, 3, 3)).view(B, repeats, 1, 3, 3)
    allc = torch.cat([models[:, :, None], ref], 2).view(B, repeats * 2, 3, 3)
    models, inl = _pick(allc, homography_error_sq(allc, xi, xj), thr_sq, m, repeats)
    res = _finalise(models, inl, 4)
    res.success &= enough
    return res


def triangulate(R: torch.Tensor, t: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor,
                pts_j: torch.Tensor) -> torch.Tensor:
    """Triangulate (B,N,2) pixel pairs with camera i at the origin and camera j at ``T_j_i = [R | t]``.

    Returns:
        (B,N,3) points in frame i (float64); their z is the depth in camera i.
    """
    Kd = K.to(torch.float64)
    B = R.shape[0]
    P1 = Kd @ torch.cat([torch.eye(3, dtype=torch.float64, device=R.device).expand(B, 3, 3),
                         torch.zeros(B, 3, 1, dtype=torch.float64, device=R.device)], -1)
    P2 = Kd @ torch.cat([R.to(torch.float64), t.to(torch.float64).reshape(B, 3, 1)], -1)
    return triangulate_points(P1, P2, pts_i.to(torch.float64), pts_j.to(torch.float64))


def ray_depths(R: torch.Tensor, t: torch.Tensor, x_i: torch.Tensor,
               x_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form two-view depths of normalised rays under ``T_j_i = [R | t]``.

    Solves ``z_j x_j = z_i R x_i + t`` in the least-squares sense of the cross product with ``x_j``:
    ``z_i = -((x_j x t) . (x_j x R x_i)) / |x_j x R x_i|^2``; exact on exact data, and much cheaper than a
    per-point SVD.

    Args:
        R: (B,M,3,3), t: (B,M,3) candidate motions. x_i, x_j: (B,N,2) normalised coordinates.

    Returns:
        z_i, z_j: (B,M,N) depths in cameras i and j.
    """
    hi = torch.cat([x_i, torch.ones_like(x_i[..., :1])], -1)
    hj = torch.cat([x_j, torch.ones_like(x_j[..., :1])], -1)
    Rx = torch.einsum("bmrc,bnc->bmnr", R, hi)
    a = torch.linalg.cross(hj[:, None].expand_as(Rx), Rx, dim=-1)
    b = torch.linalg.cross(hj[:, None].expand_as(Rx), t[:, :, None].expand_as(Rx), dim=-1)
    z_i = -(a * b).sum(-1) / (a * a).sum(-1).clamp_min(1e-30)
    z_j = z_i * Rx[..., 2] + t[:, :, None, 2]
    return z_i, z_j


def decompose_essential(E: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor, pts_j: torch.Tensor,
                        mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Decompose E into ``T_j_i = [R | t]`` (unit t): of the four solutions of kornia's
    ``decompose_essential_matrix``, keep the one with most valid rows in front of both cameras (cheirality,
    as kornia's ``motion_from_essential_choose_solution`` does, with closed-form depths :func:`ray_depths`).

    Returns:
        R (B,3,3), t (B,3) float64, and ``in_front`` (B,N) bool: valid rows passing cheirality.
    """
    _check(pts_i, pts_j, mask, K, "decompose_essential")
    Kd = K.to(torch.float64)
    xi, xj = normalise_points(pts_i.to(torch.float64), Kd), normalise_points(pts_j.to(torch.float64), Kd)
    finite = torch.isfinite(E).all(-1).all(-1)
    safe = torch.where(finite[:, None, None], E.to(torch.float64), torch.eye(3, dtype=torch.float64, device=E.device))
    R1, R2, t = decompose_essential_matrix(safe)
    t = t.reshape(-1, 3)
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    Rs = torch.stack([R1, R1, R2, R2], 1)
    ts = torch.stack([t, -t, t, -t], 1)
    z_i, z_j = ray_depths(Rs, ts, xi, xj)
    front = mask[:, None] & (z_i > 0) & (z_j > 0) & finite[:, None, None]
    best = front.sum(-1).argmax(-1)
    ar = torch.arange(E.shape[0], device=E.device)
    return Rs[ar, best], ts[ar, best], front[ar, best]
