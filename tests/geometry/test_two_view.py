"""Two-view geometry: exact essential/homography recovery, cheirality, two-view depths, batching and padding,
OpenCV comparison."""

import math

import pytest
import torch
from kornia.geometry.epipolar import triangulate_points

from dfvo.geometry.camera import project_points, transform_points
from dfvo.geometry.se3 import direction_error_deg, pose_from_axis_angle, rotation_error_deg
from dfvo.geometry.two_view import (
    decompose_essential,
    find_essential_ransac,
    find_homography_ransac,
    homography_error_sq,
    normalise_points,
    ray_depths,
)

torch.set_num_threads(1)


def make_pairs(B: int, N: int, seed: int = 0, planar: bool = False):
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[718.0, 0.0, 320.0], [0.0, 716.0, 96.0], [0.0, 0.0, 1.0]], dtype=torch.float64).repeat(B, 1, 1)
    z = torch.full((B, N), 12.0, dtype=torch.float64) if planar else torch.rand(B, N, generator=g).double() * 40 + 5
    X = torch.stack([(torch.rand(B, N, generator=g).double() - 0.5) * 0.8 * z,
                     (torch.rand(B, N, generator=g).double() - 0.5) * 0.25 * z, z], -1)
    aa = (torch.rand(B, 3, generator=g).double() - 0.5) * 0.1
    t = torch.cat([(torch.rand(B, 2, generator=g).double() - 0.5) * 0.4, -torch.ones(B, 1).double()], -1)
    T = pose_from_axis_angle(aa, t)  # T_cur_prev
    pi, _ = project_points(X, K)
    pj, _ = project_points(transform_points(T, X), K)
    return pi, pj, K, T, X


def gens(B, seed=0):
    return [torch.Generator().manual_seed(seed + b) for b in range(B)]


def test_exact_essential_recovers_pose():
    pi, pj, K, T, _ = make_pairs(3, 500)
    mask = torch.ones(3, 500, dtype=torch.bool)
    res = find_essential_ransac(pi, pj, mask, K, generators=gens(3))
    assert res.success.all() and (res.num_inliers == 500).all()
    R, t, front = decompose_essential(res.model, K, pi, pj, mask)
    assert (rotation_error_deg(R, T[:, :3, :3]) < 1e-3).all()
    assert (direction_error_deg(t, T[:, :3, 3]) < 1e-2).all()
    assert front.all()
    assert torch.allclose(t.norm(dim=-1), torch.ones(3, dtype=torch.float64))


def test_threshold_in_pixels_separates_outliers():
    pi, pj, K, T, _ = make_pairs(1, 400, seed=1)
    mask = torch.ones(1, 400, dtype=torch.bool)
    bad = torch.zeros(1, 400, dtype=torch.bool)
    bad[:, ::4] = True
    g = torch.Generator().manual_seed(3)
    direction = torch.nn.functional.normalize(torch.randn(1, 400, 2, generator=g, dtype=torch.float64), dim=-1)
    pj = torch.where(bad[..., None], pj + direction * 15.0, pj)
    res = find_essential_ransac(pi, pj, mask, K, threshold_px=0.2, generators=gens(1))
    assert torch.equal(res.inliers, ~bad)
    # padding rows are never inliers and never sampled
    mask2 = mask.clone()
    mask2[:, 300:] = False
    res2 = find_essential_ransac(pi, pj, mask2, K, threshold_px=0.2, generators=gens(1))
    assert not res2.inliers[:, 300:].any() and torch.equal(res2.inliers[:, :300], ~bad[:, :300])


def test_batched_equals_unbatched_and_seed_stable():
    pi, pj, K, _, _ = make_pairs(3, 300, seed=2)
    pj = pj + 0.3 * torch.randn(pj.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    mask = torch.ones(3, 300, dtype=torch.bool)
    full = find_essential_ransac(pi, pj, mask, K, threshold_px=0.5, generators=gens(3, 7))
    again = find_essential_ransac(pi, pj, mask, K, threshold_px=0.5, generators=gens(3, 7))
    assert torch.equal(full.model, again.model) and torch.equal(full.inliers, again.inliers)
    for b in range(3):
        one = find_essential_ransac(pi[b:b + 1], pj[b:b + 1], mask[b:b + 1], K[b:b + 1], threshold_px=0.5,
                                    generators=[torch.Generator().manual_seed(7 + b)])
        assert torch.equal(one.inliers[0], full.inliers[b])
        assert torch.allclose(one.model[0], full.model[b], atol=1e-9)


def test_padding_and_batch_do_not_change_a_frames_result():
    """Extra padding rows (masked, garbage values) and other frames in the batch leave E and H unchanged."""
    pi, pj, K, _, _ = make_pairs(2, 300, seed=6)
    g = torch.Generator().manual_seed(1)
    pj = pj + 0.3 * torch.randn(pj.shape, generator=g, dtype=torch.float64)
    pj[:, :60] += 20.0
    mask = torch.ones(2, 300, dtype=torch.bool)
    pad_i = torch.cat([pi, torch.full((2, 40, 2), float("nan"), dtype=torch.float64)], 1)
    pad_j = torch.cat([pj, torch.full((2, 40, 2), 1e9, dtype=torch.float64)], 1)
    pad_m = torch.cat([mask, torch.zeros(2, 40, dtype=torch.bool)], 1)
    for fn, kw in ((find_essential_ransac, {"K": K, "threshold_px": 0.5}), (find_homography_ransac, {})):
        ref = fn(pi, pj, mask, generators=gens(2, 3), **kw)
        padded = fn(pad_i, pad_j, pad_m, generators=gens(2, 3), **kw)
        assert torch.allclose(padded.model, ref.model, atol=1e-9, equal_nan=True)
        assert torch.equal(padded.inliers[:, :300], ref.inliers) and not padded.inliers[:, 300:].any()
        one = fn(pi[1:], pj[1:], mask[1:], generators=gens(1, 4), **{k: (v[1:] if k == "K" else v)
                                                                         for k, v in kw.items()})
        assert torch.allclose(one.model[0], ref.model[1], atol=1e-9) and torch.equal(one.inliers[0], ref.inliers[1])


def test_too_few_points_fail_and_bad_shapes_raise():
    pi, pj, K, _, _ = make_pairs(1, 20)
    mask = torch.zeros(1, 20, dtype=torch.bool)
    mask[:, :4] = True
    assert not find_essential_ransac(pi, pj, mask, K, generators=gens(1)).success.any()
    with pytest.raises(Exception, match="find_essential_ransac"):
        find_essential_ransac(pi, pj[:, :10], mask, K)


def test_ray_depths_match_truth_and_kornia_triangulation():
    pi, pj, K, T, X = make_pairs(2, 100, seed=4)
    xi, xj = normalise_points(pi, K), normalise_points(pj, K)
    z_i, z_j = ray_depths(T[:, None, :3, :3], T[:, None, :3, 3], xi, xj)
    assert torch.allclose(z_i[:, 0], X[..., 2], rtol=1e-9)
    assert torch.allclose(z_j[:, 0], transform_points(T, X)[..., 2], rtol=1e-9)
    P1 = K @ torch.eye(4, dtype=torch.float64)[:3].expand(2, 3, 4)
    P2 = K @ T[:, :3]
    assert torch.allclose(triangulate_points(P1, P2, pi, pj), X, rtol=1e-6)


def test_homography_error_hand_derived_and_ransac_on_plane():
    # H = I, only image j displaced by d: first-order geometric error = |d|^2 / 2
    x = torch.rand(1, 50, 2, dtype=torch.float64) * 100
    d = torch.randn(1, 50, 2, dtype=torch.float64)
    e = homography_error_sq(torch.eye(3, dtype=torch.float64)[None, None], x, x + d)[:, 0]
    assert torch.allclose(e, (d**2).sum(-1) / 2, rtol=1e-9)
    pi, pj, K, T, _ = make_pairs(2, 300, seed=5, planar=True)
    mask = torch.ones(2, 300, dtype=torch.bool)
    h = find_homography_ransac(pi, pj, mask, generators=gens(2))
    assert (h.num_inliers == 300).all()
    err = homography_error_sq(h.model[:, None], pi, pj)[:, 0]
    assert err.max() < 1e-12


@pytest.mark.parametrize("outlier_fraction", [0.2, 0.4])
def test_noisy_with_outliers_at_least_as_good_as_opencv(outlier_fraction):
    cv2 = pytest.importorskip("cv2")
    import numpy as np

    ours_r, ours_t, cv_r, cv_t = [], [], [], []
    for trial in range(4):
        pi, pj, K, T, _ = make_pairs(1, 1000, seed=10 + trial)
        g = torch.Generator().manual_seed(100 + trial)
        pj = pj + 0.3 * torch.randn(pj.shape, generator=g, dtype=torch.float64)
        n_out = int(outlier_fraction * 1000)
        pj[:, :n_out] += (torch.rand(1, n_out, 2, generator=g, dtype=torch.float64) - 0.5) * 80
        mask = torch.ones(1, 1000, dtype=torch.bool)
        res = find_essential_ransac(pi, pj, mask, K, threshold_px=1.0, generators=gens(1, trial))
        R, t, _ = decompose_essential(res.model, K, pi, pj, mask)
        ours_r.append(float(rotation_error_deg(R, T[:, :3, :3])[0]))
        ours_t.append(float(direction_error_deg(t, T[:, :3, 3])[0]))
        a, b, Kn = pi[0].numpy(), pj[0].numpy(), K[0].numpy()
        E, m = cv2.findEssentialMat(a, b, Kn, method=cv2.RANSAC, prob=0.99, threshold=1.0)
        _, Rc, tc, _ = cv2.recoverPose(E[:3], a, b, Kn, mask=m)
        cv_r.append(float(rotation_error_deg(torch.from_numpy(Rc)[None], T[:, :3, :3])[0]))
        cv_t.append(float(direction_error_deg(torch.from_numpy(np.ascontiguousarray(tc[:, 0]))[None],
                                              T[:, :3, 3])[0]))
    assert sum(ours_r) <= sum(cv_r) * 1.05 + 1e-3, (ours_r, cv_r)
    assert sum(ours_t) <= sum(cv_t) * 1.05 + 1e-2, (ours_t, cv_t)
    assert max(ours_r) < 0.2 and math.isfinite(max(ours_t))
