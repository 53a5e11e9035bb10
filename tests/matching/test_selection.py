"""Correspondence selection: best-N, local best-K, uniform, failure rule, cropping, batching."""

import numpy as np
import pytest
import torch

from dfvo.matching.selection import select_correspondences

H, W = 47, 83  # not divisible by the 10x10 grid


def _inputs(B=2, seed=0, high=0.2):
    g = torch.Generator().manual_seed(seed)
    flow = torch.randn(B, 2, H, W, generator=g) * 3
    incon = torch.rand(B, 1, H, W, generator=g) * high
    return flow, incon


def _flat(c, b):
    m = c.mask[b]
    pts = c.pts_i[b][m].round().long()
    return (pts[:, 1] * W + pts[:, 0]).tolist()


def _check_targets(c, flow):
    for b in range(flow.shape[0]):
        m = c.mask[b]
        u, v = c.pts_i[b][m, 0].long(), c.pts_i[b][m, 1].long()
        assert torch.allclose(c.pts_j[b][m], c.pts_i[b][m] + flow[b, :, v, u].T)
        assert (c.pts_i[b][~m] == 0).all() and (c.pts_j[b][~m] == 0).all()


def test_best_n_picks_exactly_the_n_smallest():
    flow, incon = _inputs()
    incon[0, 0, 5:9, 10:20] = float("inf")
    c = select_correspondences(flow, incon, method="best_n", num=300)
    assert c.pts_i.shape == (2, 300, 2) and c.mask.shape == (2, 300)
    for b in range(2):
        ref = np.argsort(incon[b, 0].reshape(-1).numpy(), kind="stable")[:300]
        assert sorted(_flat(c, b)) == sorted(ref.tolist())
        assert torch.allclose(c.inconsistency[b], incon[b, 0].reshape(-1)[torch.as_tensor(_flat(c, b))])
    assert not c.failed.any() and c.reasons == [None, None]
    _check_targets(c, flow)


def _edges(n, parts):
    return [(k * n) // parts for k in range(parts + 1)]


def test_local_best_k_matches_direct_loop():
    flow, incon = _inputs(B=2, seed=1)
    # region (row 0, col 0) keeps a single valid pixel: K_j = min(K, Q_j) = 1
    incon[0, 0, :4, :8] = 0.5
    incon[0, 0, 1, 2] = 0.01
    num, k = 500, 5
    c = select_correspondences(flow, incon, method="local_best_k", num=num, grid=(10, 10), max_inconsistency=0.1)
    rows, cols = _edges(H, 10), _edges(W, 10)
    for b in range(2):
        got = set(_flat(c, b))
        expected = set()
        for a in range(10):
            for cc in range(10):
                block = incon[b, 0, rows[a] : rows[a + 1], cols[cc] : cols[cc + 1]].numpy()
                vv, uu = np.meshgrid(np.arange(rows[a], rows[a + 1]), np.arange(cols[cc], cols[cc + 1]),
                                     indexing="ij")
                vals, flat = block.reshape(-1), (vv * W + uu).reshape(-1)
                keep = vals < 0.1
                order = np.argsort(vals[keep], kind="stable")[:k]
                expected.update(flat[keep][order].tolist())
                sel = [p for p in got if rows[a] <= p // W < rows[a + 1] and cols[cc] <= p % W < cols[cc + 1]]
                assert len(sel) <= k
        assert got == expected
        assert (c.inconsistency[b][c.mask[b]] < 0.1).all()
    assert (1 * W + 2) in set(_flat(c, 0))
    assert int(c.mask[0].sum()) == 99 * k + 1
    _check_targets(c, flow)
    # real rows first
    for b in range(2):
        n = int(c.mask[b].sum())
        assert c.mask[b, :n].all() and not c.mask[b, n:].any()


def test_black_frame_fails_with_reason():
    flow, incon = _inputs(B=2)
    incon[1] = float("inf")
    for method in ("local_best_k", "best_n", "uniform"):
        c = select_correspondences(flow, incon, method=method, num=400)
        assert c.failed.tolist() == [False, True]
        assert c.reasons[0] is None and "only 0 pixels" in c.reasons[1]
        assert not c.mask[1].any()


def test_too_few_regions_fails_even_with_enough_pixels():
    flow, incon = _inputs(B=1)
    incon[:] = 1.0
    incon[0, 0, :4, :8] = 0.0  # plenty of valid pixels, all in one region
    c = select_correspondences(flow, incon, method="local_best_k", num=200)
    assert bool(c.failed[0])
    assert "1 of 100 regions" in c.reasons[0]
    assert "pixels with" not in c.reasons[0]  # 32 valid pixels >= 0.1 * 200: only the region rule fires
    # lowering the region rule rescues it
    c2 = select_correspondences(flow, incon, method="local_best_k", num=200, min_region_fraction=0.01)
    assert not bool(c2.failed[0]) and c2.reasons[0] is None


def test_too_few_valid_pixels_fails():
    flow, incon = _inputs(B=1)
    incon[:] = 1.0
    rows, cols = _edges(H, 10), _edges(W, 10)
    for a in range(10):  # one valid pixel in every region: 100 < 0.1 * 2000
        incon[0, 0, rows[a], cols[:10]] = 0.0
    c = select_correspondences(flow, incon, method="local_best_k", num=2000)
    assert bool(c.failed[0]) and "only 100 pixels" in c.reasons[0] and "regions" not in c.reasons[0]
    assert int(c.mask.sum()) == 100


def test_uniform_grid_spacing_and_random_mode():
    flow, incon = _inputs(B=2)
    incon[1, 0, :, :10] = float("inf")
    c = select_correspondences(flow, incon, method="uniform", num=400)
    pts = c.pts_i[0][c.mask[0]]
    us, vs = torch.unique(pts[:, 0]), torch.unique(pts[:, 1])
    assert len(us) * len(vs) == pts.shape[0] <= 400 and pts.shape[0] >= 0.9 * 400
    du, dv = torch.diff(us), torch.diff(vs)
    assert du.max() - du.min() <= 1 and dv.max() - dv.min() <= 1  # evenly spaced up to integer rounding
    assert us.min() >= 0 and us.max() <= W - 1 and vs.min() >= 0 and vs.max() <= H - 1
    assert (W - 1 - us.max()) - us.min() <= du.max() and (H - 1 - vs.max()) - vs.min() <= dv.max()  # centred
    assert (c.pts_i[1][c.mask[1]][:, 0] >= 10).all()  # rows with infinite inconsistency are masked
    # random mode: reproducible with the generator, distinct pixels, exactly num of them
    r1 = select_correspondences(flow, incon, method="uniform", num=400, generator=torch.Generator().manual_seed(5))
    r2 = select_correspondences(flow, incon, method="uniform", num=400, generator=torch.Generator().manual_seed(5))
    r3 = select_correspondences(flow, incon, method="uniform", num=400, generator=torch.Generator().manual_seed(6))
    assert torch.equal(r1.pts_i, r2.pts_i) and not torch.equal(r1.pts_i, r3.pts_i)
    assert len(set(_flat(r1, 0))) == 400
    _check_targets(r1, flow)


def test_crop_top_excludes_rows_and_retiles_regions():
    flow, incon = _inputs(B=1)
    top = round(0.3 * H)
    for method in ("local_best_k", "best_n", "uniform"):
        c = select_correspondences(flow, incon, method=method, num=300, crop_top=0.3)
        assert (c.pts_i[0][c.mask[0]][:, 1] >= top).all()
    c = select_correspondences(flow, incon, method="local_best_k", num=300, crop_top=0.3)
    assert int(c.mask.sum()) == 300  # every one of the 100 regions tiles kept rows and gives K = 3
    with pytest.raises(Exception, match="crop_top"):
        select_correspondences(flow, incon, crop_top=1.0)
    with pytest.raises(Exception, match="method"):
        select_correspondences(flow, incon, method="best_k")


def test_batched_equals_single():
    flow, incon = _inputs(B=3, seed=4, high=0.15)
    incon[2] = float("inf")
    for method in ("local_best_k", "best_n", "uniform"):
        full = select_correspondences(flow, incon, method=method, num=500)
        for b in range(3):
            one = select_correspondences(flow[b : b + 1], incon[b : b + 1], method=method, num=500)
            assert torch.equal(full.mask[b], one.mask[0])
            assert torch.equal(full.pts_i[b], one.pts_i[0]) and torch.equal(full.pts_j[b], one.pts_j[0])
            assert full.reasons[b] == one.reasons[0] and bool(full.failed[b]) == bool(one.failed[0])


def test_fewer_rows_than_regions_never_exceeds_num():
    flow, incon = _inputs(B=2, seed=7)
    c = select_correspondences(flow, incon, method="local_best_k", num=40, min_valid_fraction=0.0)
    assert c.pts_i.shape == (2, 40, 2) and c.mask.all()
    rows, cols = _edges(H, 10), _edges(W, 10)
    for b in range(2):
        winners = []
        for a in range(10):
            for cc in range(10):
                block = incon[b, 0, rows[a] : rows[a + 1], cols[cc] : cols[cc + 1]]
                if (block < 0.1).any():
                    winners.append(float(block[block < 0.1].min()))
        assert sorted(c.inconsistency[b].tolist()) == pytest.approx(sorted(winners)[:40])


def test_min_texture_drops_flat_pixels_whatever_their_consistency():
    """Image i textured (noise) on its left half and flat on its right half; every pixel perfectly consistent. With
    ``min_texture`` the selection takes only left-half pixels, exactly the local best-K of the inconsistency with the
    flat half set unusable; without it both halves; a frame whose texture is all flat fails and says why."""
    from dfvo.matching.image_ops import shi_tomasi

    g = torch.Generator().manual_seed(3)
    img = torch.full((1, 1, 96, 160), 0.5)
    img[..., :80] = torch.rand(1, 1, 96, 80, generator=g)
    texture = shi_tomasi(img, 11, 1.0)
    assert float(texture[..., :, :70].min()) > 1e-4 and float(texture[..., :, 90:].max()) < 1e-8
    flow = torch.randn(1, 2, 96, 160, generator=g)
    incon = torch.rand(1, 1, 96, 160, generator=g) * 0.05
    gated = select_correspondences(flow, incon, num=2000, texture=texture, min_texture=1e-5)
    plain = select_correspondences(flow, incon, num=2000)
    assert float(gated.pts_i[0][gated.mask[0], 0].max()) < 90 and float(plain.pts_i[0][plain.mask[0], 0].max()) > 150
    ref = select_correspondences(flow, incon.masked_fill(texture < 1e-5, float("inf")), num=2000)
    assert torch.equal(gated.pts_i, ref.pts_i) and torch.equal(gated.mask, ref.mask)
    flat = select_correspondences(flow, incon, num=2000, texture=torch.zeros_like(texture), min_texture=1e-5)
    assert bool(flat.failed[0]) and "texture >= 1e-05" in flat.reasons[0]
    with pytest.raises(Exception, match="min_texture=1e-05 needs the"):
        select_correspondences(flow, incon, num=2000, min_texture=1e-5)
