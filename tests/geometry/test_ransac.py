"""The shared batched RANSAC loop: sampling (distinct, uniform, batch- and padding-invariant), ranking, and a
toy model (2-D lines) with a known truth."""

import pytest
import torch

from dfvo.geometry.ransac import (
    frame_rand,
    hypothesise_and_verify,
    pick_best,
    rank_models,
    sample_rows,
    sample_rows_with_replacement,
    score_models,
)

torch.set_num_threads(1)


def gens(B, seed=0):
    return [torch.Generator().manual_seed(seed + b) for b in range(B)]


def test_frame_rand_is_per_frame():
    a = frame_rand(gens(3, 5), 3, (4, 7), torch.device("cpu"))
    b = frame_rand(gens(1, 6), 1, (4, 7), torch.device("cpu"))
    assert a.shape == (3, 4, 7) and a.dtype == torch.float64 and torch.equal(a[1], b[0])
    with pytest.raises(Exception, match="frame_rand"):
        frame_rand(gens(2), 3, (4,), torch.device("cpu"))


def test_sample_rows_distinct_valid_batch_and_padding_invariant():
    B, N, S, k = 3, 40, 500, 6
    mask = torch.rand(B, N, generator=torch.Generator().manual_seed(1)) < 0.6
    rows = sample_rows(mask, S, k, gens(B))
    assert rows.shape == (B, S, k)
    assert mask.gather(1, rows.view(B, -1)).all()  # only valid rows
    srt = rows.sort(-1).values
    assert (srt[..., 1:] != srt[..., :-1]).all()  # distinct within each subset
    for b in range(B):  # alone, and padded with 25 invalid rows in front and behind: the same rows
        assert torch.equal(sample_rows(mask[b:b + 1], S, k, gens(1, b))[0], rows[b])
        off = torch.zeros(1, 10, dtype=torch.bool)
        padded = torch.cat([off, mask[b:b + 1], off[:, :5].repeat(1, 3)], 1)
        assert torch.equal(sample_rows(padded, S, k, gens(1, b))[0] - 10, rows[b])


def test_sample_rows_are_uniform():
    N, S, k = 20, 20000, 5
    mask = torch.ones(1, N, dtype=torch.bool)
    mask[0, ::4] = False  # 15 valid rows
    counts = torch.bincount(sample_rows(mask, S, k, gens(1)).flatten(), minlength=N).double()
    expected = S * k / 15
    assert (counts[~mask[0]] == 0).all()
    assert ((counts[mask[0]] - expected).abs() / expected).max() < 0.05
    draws = sample_rows_with_replacement(mask, 30000, gens(1))
    counts = torch.bincount(draws.flatten(), minlength=N).double()
    assert (counts[~mask[0]] == 0).all() and ((counts[mask[0]] - 2000).abs() / 2000).max() < 0.1


def test_ranking_counts_then_truncated_error_then_first():
    thr = 1.0
    # model 0: 2 inliers (errors 0.5, 0.5); model 1: 2 inliers (0.1, 0.1); model 2: same as 1; model 3: 1 inlier
    err = torch.tensor([[[0.5, 0.5, 9.0], [0.1, 0.1, 9.0], [0.1, 0.1, 9.0], [0.0, 9.0, 9.0]]], dtype=torch.float64)
    mask = torch.ones(1, 3, dtype=torch.bool)
    count, trunc = score_models(err, thr, mask)
    assert count.tolist() == [[2, 2, 2, 1]] and trunc.tolist() == [[2.0, 1.2, 1.2, 2.0]]
    assert rank_models(count, trunc, thr, 3).tolist() == [[1, 2, 0, 3]]
    models = torch.arange(4, dtype=torch.float64).view(1, 4, 1)
    model, inliers, idx = pick_best(models, err, thr, mask)
    assert int(idx) == 1 and float(model) == 1.0 and inliers.tolist() == [[True, True, False]]
    # non-finite errors and masked rows never count
    err2 = torch.tensor([[[float("nan"), 0.1, 0.1]]], dtype=torch.float64)
    assert score_models(err2, thr, torch.tensor([[True, True, False]]))[0].tolist() == [[1]]


def _lines(B, N, seed):
    """Points on y = a x + b with 0.01 noise and 30 % gross outliers; returns pts (B,N,2), truth (B,2)."""
    g = torch.Generator().manual_seed(seed)
    ab = torch.randn(B, 2, generator=g, dtype=torch.float64)
    x = torch.rand(B, N, generator=g, dtype=torch.float64) * 10 - 5
    y = ab[:, :1] * x + ab[:, 1:] + 0.01 * torch.randn(B, N, generator=g, dtype=torch.float64)
    out = torch.rand(B, N, generator=g) < 0.3
    y = torch.where(out, y + 5 + 10 * torch.rand(B, N, generator=g, dtype=torch.float64), y)
    return torch.stack([x, y], -1), ab


def _line_fns(pts):
    def solve(rows):  # (B,S,2) -> (B,S,1,2) lines (a, b) through the two points
        B, S, _ = rows.shape
        p = pts.gather(1, rows.view(B, -1, 1).expand(-1, -1, 2)).view(B, S, 2, 2)
        a = (p[..., 1, 1] - p[..., 0, 1]) / (p[..., 1, 0] - p[..., 0, 0])
        return torch.stack([a, p[..., 0, 1] - a * p[..., 0, 0]], -1)[:, :, None]

    def residual(models, rows, exact):
        q = pts if rows is None else pts.gather(1, rows[..., None].expand(-1, -1, 2))
        return (q[:, None, :, 1] - models[..., 0:1] * q[:, None, :, 0] - models[..., 1:2]) ** 2

    return solve, residual


@pytest.mark.parametrize("preview", [None, 64])
def test_toy_lines_recovered_and_batch_invariant(preview):
    B, N, R = 4, 300, 3
    pts, ab = _lines(B, N, seed=2)
    mask = torch.ones(B, N, dtype=torch.bool)
    solve, residual = _line_fns(pts)
    win = hypothesise_and_verify(mask, 2, solve, residual, 0.05**2, iterations=30, repeats=R, generators=gens(B),
                                 preview=preview)
    assert win.models.shape == (B, R, 2) and win.err_sq.shape == (B, R, N) and win.inliers.shape == (B, R, N)
    model, inliers, _ = pick_best(win.models, win.err_sq, 0.05**2, mask)
    assert (model - ab).abs().max() < 0.02
    truth_inl = residual(ab[:, None], None, True)[:, 0] < 0.05**2
    assert (inliers == truth_inl).float().mean() > 0.99
    for b in range(B):
        s, r = _line_fns(pts[b:b + 1])
        one = hypothesise_and_verify(mask[b:b + 1], 2, s, r, 0.05**2, iterations=30, repeats=R,
                                     generators=gens(1, b), preview=preview)
        assert torch.equal(one.models[0], win.models[b]) and torch.equal(one.inliers[0], win.inliers[b])
