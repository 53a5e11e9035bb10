"""One batched hypothesise-and-verify loop (RANSAC) shared by the essential matrix, the homography and PnP.

Convention:
    ``mask`` (B,N) bool marks the real rows of padded correspondences. A minimal solver maps sampled rows
    (B,S,k) long to candidate models (B,S,M,*shape) (M candidates per sample, non-finite entries for a failed
    one); a residual function maps models (B,C,*shape) and rows (B,P) long (or None: all N rows) to squared
    errors (B,C,P) (non-finite: never an inlier). A row is an inlier of a model when its squared error is
    below ``threshold_sq`` (strict). Models are compared by inlier count, ties broken by the lower truncated
    error sum (MSAC), then by the earlier index.

Randomness: frame b draws only from ``generators[b]`` (one ``torch.Generator`` per frame, None: the global
RNG), a fixed number of draws per call, and indexes its own valid rows in their order, so a frame's result
depends neither on the other frames of its batch nor on its padding (batched == one at a time).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK

__all__ = ["frame_rand", "sample_rows", "sample_rows_with_replacement", "score_models", "rank_models", "pick_best",
           "RansacWinners", "hypothesise_and_verify"]

Solver = Callable[[torch.Tensor], torch.Tensor]
Residual = Callable[[torch.Tensor, "torch.Tensor | None", bool], torch.Tensor]


def frame_rand(generators: list[torch.Generator] | None, batch: int, shape: tuple[int, ...],
               device: torch.device) -> torch.Tensor:
    """Uniform numbers in [0, 1), one draw of ``shape`` per frame.

    Convention:
        Returns (B,*shape) float64 on ``device``; frame b's numbers come from ``generators[b]`` (drawn on the
        generator's own device, then moved), or from the global RNG when ``generators`` is None.
    """
    if generators is None:
        return torch.rand((batch, *shape), dtype=torch.float64, device=device)
    KORNIA_CHECK(len(generators) == batch, f"frame_rand: {len(generators)} generators for a batch of {batch}")
    return torch.stack([torch.rand(shape, generator=g, dtype=torch.float64, device=g.device).to(device)
                        for g in generators])


def _valid_first(mask: torch.Tensor) -> torch.Tensor:
    """(B,N) long: the indices of each frame's valid rows first, in their order, then the padding."""
    return torch.sort((~mask).to(torch.uint8), dim=1, stable=True).indices


def sample_rows(mask: torch.Tensor, num_samples: int, size: int,
                generators: list[torch.Generator] | None) -> torch.Tensor:
    """Uniform random ``size``-subsets of each frame's valid rows (distinct within a subset).

    Convention:
        mask (B,N) bool with N >= size -> (B,S,size) long row indices. Frame b uses ``S * size`` draws of
        ``generators[b]``; the r-th free valid row is picked by skipping the rows already chosen, so no
        rejection and no dependence on N. A frame with fewer than ``size`` valid rows gets padding rows too
        (the caller marks such frames failed).
    """
    B, N = mask.shape
    KORNIA_CHECK(N >= size, f"sample_rows: {N} rows cannot give subsets of {size}")
    u = frame_rand(generators, B, (num_samples, size), mask.device)
    n = mask.sum(-1).clamp_min(size)[:, None]
    chosen: list[torch.Tensor] = []
    for j in range(size):
        r = torch.minimum(torch.floor(u[..., j] * (n - j)).long(), n - j - 1)
        if chosen:
            for prev in torch.sort(torch.stack(chosen, -1), dim=-1).values.unbind(-1):
                r = r + (r >= prev).long()  # step over the chosen rows, smallest first
        chosen.append(r)
    local = torch.stack(chosen, -1)  # (B,S,size) positions among the valid rows
    return _valid_first(mask).gather(1, local.view(B, -1)).view(B, num_samples, size)


def sample_rows_with_replacement(mask: torch.Tensor, count: int,
                                 generators: list[torch.Generator] | None) -> torch.Tensor:
    """Uniform draws, with replacement, among each frame's valid rows.

    Convention:
        mask (B,N) bool -> (B,count) long row indices; frame b uses ``count`` draws of ``generators[b]`` and its
        valid rows in order (independent of N and of the batch); a frame without valid rows gets row 0.
    """
    B = mask.shape[0]
    u = frame_rand(generators, B, (count,), mask.device)
    n = mask.sum(-1, keepdim=True)
    local = torch.minimum(torch.floor(u * n).long(), (n - 1).clamp_min(0))
    return _valid_first(mask).gather(1, local)


def score_models(err_sq: torch.Tensor, threshold_sq: float, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inlier counts and truncated error sums of (B,C,P) squared errors over the rows ``mask`` (B,P).

    Convention:
        Returns counts (B,C) long (rows with finite error < ``threshold_sq``) and the MSAC sums (B,C) float64
        of ``min(err, threshold_sq)`` (``threshold_sq`` for NaN errors), summed in the dtype of ``err_sq``.
    """
    inl = (err_sq < threshold_sq).logical_and_(mask[:, None, :])  # NaN compares False
    count = inl.sum(-1)
    # sum of min(err, thr) over the valid rows = inliers' errors + thr for every other valid row
    inlier_err = torch.where(inl, err_sq, 0.0).sum(-1).to(torch.float64)
    return count, inlier_err + threshold_sq * (mask.sum(-1, keepdim=True) - count)


def _key(count: torch.Tensor, trunc: torch.Tensor, threshold_sq: float, rows: int) -> torch.Tensor:
    """Ranking key: the count, minus a fraction in [0, 1) that grows with the truncated error."""
    return count.to(torch.float64) - trunc / (max(threshold_sq, 1e-300) * (rows + 1))


def rank_models(count: torch.Tensor, trunc: torch.Tensor, threshold_sq: float, rows: int) -> torch.Tensor:
    """(B,C) long: candidate indices per frame, best first (most inliers, then lowest truncated error, then first).

    Convention:
        count (B,C), trunc (B,C) from :func:`score_models` over ``rows`` rows.
    """
    return torch.sort(_key(count, trunc, threshold_sq, rows), dim=-1, descending=True, stable=True).indices


def _take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B,C,*s), idx (B,*k) long -> (B,*k,*s)."""
    B, s = x.shape[0], x.shape[2:]
    flat = idx.reshape(B, -1)
    out = x.gather(1, flat.view(B, -1, *([1] * len(s))).expand(B, flat.shape[1], *s))
    return out.view(*idx.shape, *s)


def pick_best(models: torch.Tensor, err_sq: torch.Tensor, threshold_sq: float,
              mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The best of C candidate models per frame (most inliers, then lowest truncated error, then first).

    Convention:
        models (B,C,*shape), err_sq (B,C,N) their squared errors on all rows, mask (B,N) bool. Returns the
        chosen model (B,*shape), its inliers (B,N) bool and its index (B,) long.
    """
    count, trunc = score_models(err_sq, threshold_sq, mask)
    best = _key(count, trunc, threshold_sq, err_sq.shape[-1]).argmax(-1)
    e = _take(err_sq, best[:, None])[:, 0]
    return _take(models, best[:, None])[:, 0], mask & torch.isfinite(e) & (e < threshold_sq), best


@dataclass
class RansacWinners:
    """The winner of each repeat of :func:`hypothesise_and_verify`.

    Convention:
        B frames, R repeats, N rows; ``*shape`` is the model's shape (e.g. (3,3) for E and H, (3,4) for PnP).

    Attributes:
        models: (B,R,*shape) each repeat's best candidate.
        err_sq: (B,R,N) their squared errors on all rows (``residual_sq(models, None, True)``).
        inliers: (B,R,N) bool valid rows with ``err_sq < threshold_sq``.
    """

    models: torch.Tensor
    err_sq: torch.Tensor
    inliers: torch.Tensor


def hypothesise_and_verify(mask: torch.Tensor, sample_size: int, solve: Solver, residual_sq: Residual,
                           threshold_sq: float, iterations: int, repeats: int,
                           generators: list[torch.Generator] | None, preview: int | None = None,
                           chunk_elements: int = 200_000) -> RansacWinners:
    """Batched RANSAC: ``repeats`` independent repeats of ``iterations`` minimal samples each, all frames at once.

    Each repeat keeps its best candidate (most inliers, ties by truncated error, then the earlier sample);
    refinement and the choice among repeats are left to the caller (:func:`pick_best`).

    Convention:
        mask (B,N) bool valid rows, N >= ``sample_size``. ``solve(rows (B,S,k) long) -> (B,S,M,*shape)``;
        ``residual_sq(models (B,C,*shape), rows (B,P) long | None, exact) -> (B,C,P)`` squared errors, where
        ``exact=False`` may trade precision for speed (ranking only) and ``rows=None`` means all N rows.
        Candidates are ranked on ``preview`` rows drawn per frame (with replacement), or on all rows when
        ``preview`` is None; each repeat's winner is then scored exactly on all rows. Scoring runs in chunks
        of about ``chunk_elements`` (frame, candidate, row) triples.
        The draws of frame b, from ``generators[b]``: the samples, then the preview rows.

    Returns:
        :class:`RansacWinners` with (B,R,...) tensors.
    """
    KORNIA_CHECK(iterations > 0 and repeats > 0, f"hypothesise_and_verify: need iterations, repeats > 0; got "
                                                 f"{iterations}, {repeats}")
    B, N = mask.shape
    rows = sample_rows(mask, iterations * repeats, sample_size, generators)
    cand = solve(rows)
    M, shape = cand.shape[2], cand.shape[3:]
    cand = cand.reshape(B, iterations * repeats * M, *shape)
    if preview is None:
        sub, sub_mask = None, mask
    else:
        sub = sample_rows_with_replacement(mask, preview, generators)
        sub_mask = mask.gather(1, sub)
    P = sub_mask.shape[1]
    chunk = max(1, chunk_elements // max(B * P, 1))  # keep each chunk's (B,chunk,P) errors in cache
    counts, truncs = [], []
    for c0 in range(0, cand.shape[1], chunk):
        c, t = score_models(residual_sq(cand[:, c0:c0 + chunk], sub, False), threshold_sq, sub_mask)
        counts.append(c)
        truncs.append(t)
    key = _key(torch.cat(counts, 1), torch.cat(truncs, 1), threshold_sq, P).view(B, repeats, iterations * M)
    best = key.argmax(-1) + torch.arange(repeats, device=mask.device)[None] * (iterations * M)
    winners = _take(cand, best)
    err = residual_sq(winners, None, True)
    return RansacWinners(winners, err, mask[:, None] & torch.isfinite(err) & (err < threshold_sq))
