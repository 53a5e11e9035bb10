"""PnP with batched RANSAC and LM refinement: exact, planar, noisy with outliers (vs OpenCV), batching, failures."""

import numpy as np
import pytest
import torch

from dfvo.geometry.lm import refine_pose_lm
from dfvo.geometry.pnp import solve_pnp_ransac
from dfvo.geometry.se3 import pose_from_axis_angle, rotation_error_deg
from dfvo.synthetic import SyntheticWorld

Hs, Ws = 192, 640


@pytest.fixture(autouse=True)
def _one_thread():
    """Single-threaded: the shared 2-core machine runs other suites at the same time."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _gens(B, seed):
    """One generator per frame: frame b draws from seed + b."""
    return [torch.Generator().manual_seed(seed + b) for b in range(B)]


def _K(B, dtype=torch.float64):
    K = torch.tensor([[718.856, 0.0, 319.5], [0.0, 718.856, 95.5], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.expand(B, 3, 3).clone()


def _scene(B=4, N=2000, seed=0, planar=False):
    """Points back-projected from random pixels of frame i at KITTI-like depths, a small forward motion."""
    g = torch.Generator().manual_seed(seed)
    K = _K(B)
    u = torch.rand(B, N, generator=g, dtype=torch.float64) * (Ws - 1)
    v = torch.rand(B, N, generator=g, dtype=torch.float64) * (Hs - 1)
    if planar:  # a road plane 1.65 m below the camera, seen in the lower half of the image
        v = Hs / 2 + 5 + torch.rand(B, N, generator=g, dtype=torch.float64) * (Hs / 2 - 6)
        z = 1.65 * K[:, 1:2, 1] / (v - K[:, 1:2, 2])
    else:
        z = 3.0 + torch.rand(B, N, generator=g, dtype=torch.float64) * 45.0
    X = torch.stack([(u - K[:, 0:1, 2]) / K[:, 0:1, 0] * z, (v - K[:, 1:2, 2]) / K[:, 1:2, 1] * z, z], -1)
    aa = torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.03
    t = torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.1 + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    T = pose_from_axis_angle(aa, t)
    Xc = X @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    p = Xc @ K.transpose(1, 2)
    return X, p[..., :2] / p[..., 2:3], K, T


def _corrupt(px, noise, outlier_ratio, seed):
    g = torch.Generator().manual_seed(seed)
    out = px + noise * torch.randn(px.shape, generator=g, dtype=px.dtype)
    is_out = torch.rand(px.shape[:2], generator=g, dtype=px.dtype) < outlier_ratio
    jump = (torch.rand(px.shape, generator=g, dtype=px.dtype) - 0.5) * 80.0
    jump = jump + 5.0 * jump.sign()
    return torch.where(is_out[..., None], out + jump, out), is_out


def _errors(T_est, T_true):
    rot = rotation_error_deg(T_est[:, :3, :3].double(), T_true[:, :3, :3].double())
    trans = (T_est[:, :3, 3].double() - T_true[:, :3, 3].double()).norm(dim=-1)
    return rot, trans


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_correspondences_give_exact_pose(dtype):
    X, px, K, T = _scene(B=3, N=500)
    mask = torch.ones(3, 500, dtype=torch.bool)
    res = solve_pnp_ransac(X.to(dtype), px.to(dtype), mask, K.to(dtype), generators=_gens(3, 0))
    assert res.T_cur_prev.shape == (3, 4, 4) and res.T_cur_prev.dtype == dtype
    assert res.success.all() and (res.num_inliers == 500).all() and res.inliers.all()
    rot, trans = _errors(res.T_cur_prev, T)
    assert rot.max() < 1e-4 and trans.max() < 1e-5


def test_planar_scene_is_solved():
    X, px, K, T = _scene(B=2, N=400, planar=True, seed=2)
    assert (X[..., 1] - 1.65).abs().max() < 1e-9  # all points on the road plane: the 12-unknown DLT is degenerate
    res = solve_pnp_ransac(X.float(), px.float(), torch.ones(2, 400, dtype=torch.bool), K.float(),
                           generators=_gens(2, 0))
    rot, trans = _errors(res.T_cur_prev, T)
    assert res.success.all() and rot.max() < 1e-4 and trans.max() < 1e-5


def test_lm_refinement_converges_from_perturbed_pose():
    X, px, K, T = _scene(B=2, N=300, seed=3)
    T0 = pose_from_axis_angle(torch.tensor([[0.02, -0.01, 0.03], [-0.02, 0.01, 0.0]], dtype=torch.float64),
                              torch.tensor([[0.1, -0.05, 0.2], [0.0, 0.1, -0.1]], dtype=torch.float64)) @ T
    T_ref, cost = refine_pose_lm(X, px, torch.ones(2, 300), K, T0, iterations=30)
    rot, trans = _errors(T_ref, T)
    assert rot.max() < 1e-8 and trans.max() < 1e-9 and cost.max() < 1e-12


def _opencv_pnp(X, px, K, threshold, iterations):
    cv2 = pytest.importorskip("cv2")
    cv2.setNumThreads(1)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X.astype(np.float64), px.astype(np.float64), K, None,
                                             iterationsCount=iterations, reprojectionError=threshold,
                                             confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    assert ok and inl is not None
    idx = inl[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(X[idx], px[idx], K, None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, tvec[:, 0]
    return T


@pytest.mark.parametrize("outlier_ratio", [0.2, 0.4])
def test_noise_and_outliers_at_least_as_good_as_opencv(outlier_ratio):
    pytest.importorskip("cv2")
    B, N = 6, 2000
    X, px, K, T = _scene(B=B, N=N, seed=10)
    noisy, is_out = _corrupt(px, 0.5, outlier_ratio, seed=11)
    res = solve_pnp_ransac(X.float(), noisy.float(), torch.ones(B, N, dtype=torch.bool), K.float(),
                           threshold_px=1.0, iterations=100, repeats=5, generators=_gens(B, 0))
    assert res.success.all()
    rot, trans = _errors(res.T_cur_prev, T)
    T_cv = torch.stack([torch.from_numpy(_opencv_pnp(X[b].numpy(), noisy[b].numpy(), K[b].numpy(), 1.0, 500))
                        for b in range(B)])
    rot_cv, trans_cv = _errors(T_cv, T)
    # mean error over the frames no worse than OpenCV's (EPnP RANSAC, 500 hypotheses, + its LM refinement)
    assert rot.mean() <= rot_cv.mean() * 1.05 + 1e-4, (rot.tolist(), rot_cv.tolist())
    assert trans.mean() <= trans_cv.mean() * 1.05 + 1e-4, (trans.tolist(), trans_cv.tolist())
    assert rot.max() < 0.05 and trans.max() < 0.02
    # inliers are (almost) only true inliers
    assert (res.inliers & is_out).sum() <= 0.01 * res.num_inliers.sum()


def test_batched_equals_unbatched_and_padding_is_ignored():
    B, N = 3, 600
    X, px, K, T = _scene(B=B, N=N, seed=20)
    noisy, _ = _corrupt(px, 0.5, 0.3, seed=21)
    mask = torch.ones(B, N, dtype=torch.bool)
    full = solve_pnp_ransac(X.float(), noisy.float(), mask, K.float(), generators=_gens(B, 1))
    for b in range(B):
        one = solve_pnp_ransac(X[b : b + 1].float(), noisy[b : b + 1].float(), mask[b : b + 1], K[b : b + 1].float(),
                               generators=_gens(1, 1 + b))
        # each frame draws from its own generator: the same hypotheses, hence the same pose and inliers
        assert torch.allclose(one.T_cur_prev[0], full.T_cur_prev[b], atol=1e-5)
        assert torch.equal(one.inliers[0], full.inliers[b])
    # frame 0 padded with garbage rows (mask False, NaN and huge values) gives the same result as unpadded
    Xp = torch.cat([X[:1], torch.full((1, 50, 3), float("nan"), dtype=torch.float64)], 1)
    pp = torch.cat([noisy[:1], torch.full((1, 50, 2), 1e9, dtype=torch.float64)], 1)
    mp = torch.cat([mask[:1], torch.zeros(1, 50, dtype=torch.bool)], 1)
    a = solve_pnp_ransac(X[:1].float(), noisy[:1].float(), mask[:1], K[:1].float(),
                         generators=_gens(1, 7))
    p = solve_pnp_ransac(Xp.float(), pp.float(), mp, K[:1].float(), generators=_gens(1, 7))
    assert torch.allclose(a.T_cur_prev, p.T_cur_prev, atol=1e-6) and torch.equal(a.inliers, p.inliers[:, :N])
    assert not p.inliers[:, N:].any()


def test_deterministic_with_fixed_generator():
    X, px, K, _ = _scene(B=2, N=800, seed=30)
    noisy, _ = _corrupt(px, 0.5, 0.3, seed=31)
    mask = torch.ones(2, 800, dtype=torch.bool)
    r1 = solve_pnp_ransac(X.float(), noisy.float(), mask, K.float(), generators=_gens(2, 3))
    r2 = solve_pnp_ransac(X.float(), noisy.float(), mask, K.float(), generators=_gens(2, 3))
    assert torch.equal(r1.T_cur_prev, r2.T_cur_prev) and torch.equal(r1.inliers, r2.inliers)


def test_failures_return_identity_without_raising():
    X, px, K, T = _scene(B=5, N=100, seed=40)
    X, px = X.float(), px.float()
    mask = torch.ones(5, 100, dtype=torch.bool)
    mask[0, 5:] = False  # too few points
    mask[1] = False  # nothing
    X[2] = X[2, :1]  # all points identical: degenerate
    px[3] = torch.rand(100, 2) * 600  # pure noise: no consensus
    res = solve_pnp_ransac(X, px, mask, K.float(), generators=_gens(5, 0))
    assert res.success.tolist() == [False, False, False, False, True]
    eye = torch.eye(4).expand(4, 4, 4)
    assert torch.equal(res.T_cur_prev[:4], eye) and not res.inliers[:4].any() and (res.num_inliers[:4] == 0).all()
    rot, trans = _errors(res.T_cur_prev[4:], T[4:])
    assert rot.max() < 1e-4 and trans.max() < 1e-5
    # fewer rows than a sample, non-finite input, bad intrinsics: still no exception
    small = solve_pnp_ransac(X[:, :4], px[:, :4], mask[:, :4], K.float())
    assert not small.success.any()
    Xn = X.clone()
    Xn[4, :10] = float("nan")
    res_nan = solve_pnp_ransac(Xn, px, mask, K.float(), generators=_gens(5, 0))
    assert bool(res_nan.success[4]) and not res_nan.inliers[4, :10].any()
    res_k = solve_pnp_ransac(X, px, mask, torch.zeros(5, 3, 3))
    assert not res_k.success.any()


def test_shape_errors():
    with pytest.raises(Exception, match="share"):
        solve_pnp_ransac(torch.zeros(2, 10, 3), torch.zeros(2, 9, 2), torch.ones(2, 10, dtype=torch.bool), _K(2))
    with pytest.raises(Exception, match="3"):
        solve_pnp_ransac(torch.zeros(2, 10, 2), torch.zeros(2, 10, 2), torch.ones(2, 10, dtype=torch.bool), _K(2))


def test_flow_to_pose_chain_on_a_slanted_plane():
    """Rigid forward/backward flows of a slanted wall -> consistency -> local best-K selection -> PnP -> exact pose."""
    from dfvo.geometry.camera import backproject_points, pixel_grid, rigid_flow
    from dfvo.matching.consistency import forward_backward_inconsistency
    from dfvo.matching.selection import select_correspondences

    H, W = 96, 320
    K = torch.tensor([[[360.0, 0.0, 159.5], [0.0, 360.0, 47.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    T_cur_prev = pose_from_axis_angle(torch.tensor([[0.01, -0.02, 0.005]], dtype=torch.float64),
                                 torch.tensor([[0.05, -0.02, -0.8]], dtype=torch.float64))
    T_prev_cur = torch.linalg.inv(T_cur_prev)

    def plane_depth(n, d):  # depth of the plane n.X = d seen by a camera at the origin
        rays = torch.cat([pixel_grid(H, W, dtype=torch.float64), torch.ones(H, W, 1, dtype=torch.float64)], -1)
        rays = rays @ torch.linalg.inv(K[0]).T
        return (d / (rays @ n)).reshape(1, 1, H, W)

    n_i = torch.tensor([0.1, -0.3, 1.0], dtype=torch.float64)
    n_i, d_i = n_i / n_i.norm(), 10.0
    n_j = T_cur_prev[0, :3, :3] @ n_i
    d_j = d_i + float(n_j @ T_cur_prev[0, :3, 3])
    depth_i, depth_j = plane_depth(n_i, d_i), plane_depth(n_j, d_j)
    fwd, bwd = rigid_flow(depth_i, T_cur_prev, K), rigid_flow(depth_j, T_prev_cur, K)
    incon = forward_backward_inconsistency(fwd, bwd)
    corr = select_correspondences(fwd, incon, method="local_best_k", num=1000, crop_top=0.3)
    assert not corr.failed.any() and corr.num_valid.item() > 500
    z = depth_i[0, 0][corr.pts_i[..., 1].long(), corr.pts_i[..., 0].long()]
    X = backproject_points(corr.pts_i, z, K)
    res = solve_pnp_ransac(X.float(), corr.pts_j.float(), corr.mask, K.float(),
                           generators=_gens(1, 0))
    rot, trans = _errors(res.T_cur_prev, T_cur_prev)
    assert bool(res.success[0]) and rot.item() < 1e-3 and trans.item() < 1e-4


@pytest.mark.parametrize("scenario", ["straight", "rotation"])
def test_synthetic_world_oracle_flow_and_depth_recover_true_motion(scenario):
    """Rendered oracle flows/depth -> consistency -> selection -> PnP, batched over 3 frame pairs."""
    from dfvo.geometry.camera import backproject_points
    from dfvo.matching.consistency import forward_backward_inconsistency
    from dfvo.matching.selection import select_correspondences

    world = SyntheticWorld(seed=1, num_frames=4, scenario=scenario)
    samples = [world.render(i, right=False) for i in range(3)]
    fwd = torch.stack([s["flow_fwd"] for s in samples])
    bwd = torch.stack([s["flow_bwd"] for s in samples])
    depth = torch.stack([s["depth"] for s in samples])
    K = torch.stack([s["K"] for s in samples]).float()
    poses = world.poses().double()
    T_true = torch.linalg.inv(poses[1:4]) @ poses[0:3]  # T_cur_prev: frame i into camera j = i + 1
    corr = select_correspondences(fwd, forward_backward_inconsistency(fwd, bwd), num=2000, crop_top=0.3)
    assert not corr.failed.any(), corr.reasons
    B = fwd.shape[0]
    flat = (corr.pts_i[..., 1] * depth.shape[-1] + corr.pts_i[..., 0]).long()
    z = depth[:, 0].reshape(B, -1).gather(1, flat)
    dynamic = torch.stack([s["dynamic_mask"] for s in samples]).reshape(B, -1).gather(1, flat)
    X = backproject_points(corr.pts_i, z, K)
    usable = corr.mask & (z > 0) & (z <= 50)  # the official depth range
    res = solve_pnp_ransac(X, corr.pts_j, usable, K, generators=_gens(B, 0))
    rot, trans = _errors(res.T_cur_prev, T_true)
    assert res.success.all() and rot.max() < 5e-3 and trans.max() < 5e-3, (rot.tolist(), trans.tolist())
    static = usable & ~dynamic  # the moving car's flow is consistent but not rigid: PnP must reject it
    assert (res.num_inliers >= 0.99 * static.sum(1)).all(), (res.num_inliers.tolist(), static.sum(1).tolist())
    assert (res.inliers & dynamic).sum() <= 0.01 * res.num_inliers.sum()
