"""The odometry loop on the synthetic world: exact trajectory, hard cases, fallbacks, batched == streaming."""

import pytest
import torch

from dfvo.synthetic import SyntheticWorld
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.config import ScaleConfig

torch.set_num_threads(1)

def make_cfg(tracker: str = "hybrid", scale_method: str = "simple", depth_views: int = 1, **scale) -> TrackerConfig:
    """A tracker configuration; one-view scale unless asked (these sequences pass the earlier frames' depth only)."""
    return TrackerConfig(mode=tracker, scale=ScaleConfig(method=scale_method, depth_views=depth_views, **scale))


def sequence(scenario: str, num_frames: int, seed: int = 0):
    w = SyntheticWorld(seed=seed, num_frames=num_frames, scenario=scenario)
    frames = [w.render(i) for i in range(len(w) - 1)]
    ff = torch.stack([f["flow_fwd"] for f in frames])
    fb = torch.stack([f["flow_bwd"] for f in frames])
    d = torch.stack([f["depth"] for f in frames])
    return w, ff, fb, d


def rpe(poses_true: torch.Tensor, results) -> torch.Tensor:
    errs = []
    for k, r in enumerate(results):
        T = torch.linalg.inv(poses_true[k]) @ poses_true[k + 1]
        errs.append((r.T_prev_cur[:3, 3] - T[:3, 3]).norm())
    return torch.stack(errs)


@pytest.fixture(scope="module")
def drive():
    return sequence("drive", 12)


def test_oracle_sequence_reproduces_true_poses(drive):
    w, ff, fb, d = drive
    res = VisualOdometry(make_cfg()).run(ff, fb, d, w.intrinsics(), batch_size=4)
    assert len(res) == len(w) - 1
    assert rpe(w.poses(), res).max() < 1e-3
    P = w.poses()
    final = torch.linalg.inv(P[0]) @ P[-1]
    assert (res[-1].T_w_cur[:3, 3] - final[:3, 3]).norm() < 1e-2
    diag = res[0].diagnostics
    assert diag.frame == 1 and diag.num_correspondences > 1000 and diag.num_inliers > 100
    assert diag.gric_e is not None and diag.gric_h is not None and diag.fallback_reason is None
    names = w.segment_names()
    # straight driving has parallax: E; the sharp turn is low-parallax for GRIC (far points fit H), so PnP
    assert all(r.diagnostics.tracker == "E" for k, r in enumerate(res) if names[k + 1] == "drive" and k < 3)
    assert all(r.diagnostics.tracker in ("E", "PnP") for r in res)


def test_batched_run_equals_streaming_steps_and_is_stable(drive):
    w, ff, fb, d = drive
    n = 6
    K = w.intrinsics()
    batched = VisualOdometry(make_cfg()).run(ff[:n], fb[:n], d[:n], K, batch_size=3)
    again = VisualOdometry(make_cfg()).run(ff[:n], fb[:n], d[:n], K, batch_size=3)
    vo = VisualOdometry(make_cfg())
    stream = [vo.step(ff[k:k + 1], fb[k:k + 1], d[k:k + 1], K[None]) for k in range(n)]
    for a, b, c in zip(batched, stream, again, strict=True):
        assert torch.allclose(a.T_w_cur, b.T_w_cur, atol=1e-9)
        assert torch.equal(a.T_w_cur, c.T_w_cur)
        assert a.diagnostics.num_inliers == b.diagnostics.num_inliers
    vo.reset()
    first = vo.step(ff[:1], fb[:1], d[:1], K[None])
    assert torch.allclose(first.T_w_cur, batched[0].T_w_cur, atol=1e-9)


@pytest.mark.parametrize("scenario", ["rotation", "planar"])
def test_degenerate_pairs_choose_pnp_by_gric(scenario):
    w, ff, fb, d = sequence(scenario, 4)
    res = VisualOdometry(make_cfg()).run(ff, fb, d, w.intrinsics())
    for r in res:
        assert r.diagnostics.tracker == "PnP", r.diagnostics
        assert r.diagnostics.gric_e > r.diagnostics.gric_h
        assert "GRIC" in r.diagnostics.fallback_reason
    assert rpe(w.poses(), res).max() < 1e-3


def test_standing_still_gives_no_spurious_translation():
    w, ff, fb, d = sequence("still", 4)
    res = VisualOdometry(make_cfg()).run(ff, fb, d, w.intrinsics())
    for r in res:
        assert r.T_prev_cur[:3, 3].norm() < 1e-3
        assert r.diagnostics.tracker != "E"


def test_black_frame_fails_selection_and_uses_constant_motion(drive):
    """The paper's rule (no relaxed bounds): a pair with nothing forward-backward consistent repeats the previous
    motion. With the default relaxed bounds, the same pair (its forward flow exact, its backward flow noise of 5 px)
    finds the few hundred pixels that noise puts within 0.8 px, flags them, and its exact forward flow gives the true
    step; with the forward flow noise too, it still ends in constant motion."""
    from dataclasses import replace

    w, ff, fb, d = drive
    K = w.intrinsics()[None]
    cfg = make_cfg()
    paper = replace(cfg, correspondence=replace(cfg.correspondence, relaxed_inconsistency=[]))
    vo = VisualOdometry(paper)
    first = vo.step(ff[:1], fb[:1], d[:1], K)
    # a black current frame: the network's backward flow is noise, nothing is forward-backward consistent
    noise = torch.randn(fb[1:2].shape, generator=torch.Generator().manual_seed(0)) * 5.0
    black = vo.step(ff[1:2], noise, d[1:2], K)
    assert black.diagnostics.tracker == "constant_motion"
    assert black.diagnostics.selection_failed
    assert "selection failed" in black.diagnostics.fallback_reason
    assert torch.equal(black.T_prev_cur, first.T_prev_cur)
    assert torch.allclose(black.T_w_cur, first.T_w_cur @ first.T_prev_cur)
    vo = VisualOdometry(cfg)
    first = vo.step(ff[:1], fb[:1], d[:1], K)
    relaxed = vo.step(ff[1:2], noise, d[1:2], K)
    assert relaxed.diagnostics.selection_max_inconsistency is not None and not relaxed.diagnostics.selection_failed
    T = torch.linalg.inv(w.poses()[1]) @ w.poses()[2]
    assert float((relaxed.T_prev_cur[:3, 3] - T[:3, 3]).norm()) < 1e-2
    vo = VisualOdometry(cfg)
    first = vo.step(ff[:1], fb[:1], d[:1], K)
    garbage = vo.step(torch.randn(ff[1:2].shape, generator=torch.Generator().manual_seed(1)) * 5.0, noise, d[1:2], K)
    assert garbage.diagnostics.tracker == "constant_motion" and torch.equal(garbage.T_prev_cur, first.T_prev_cur)


def test_pnp_only_tracker_is_exact(drive):
    w, ff, fb, d = drive
    res = VisualOdometry(make_cfg(tracker="pnp")).run(ff[:3], fb[:3], d[:3], w.intrinsics())
    assert all(r.diagnostics.tracker == "PnP" for r in res)
    assert rpe(w.poses(), res).max() < 1e-3


def test_bad_inputs_raise():
    vo = VisualOdometry()
    with pytest.raises(Exception, match="VisualOdometry"):
        vo.step(torch.zeros(1, 2, 8, 8), torch.zeros(1, 2, 8, 8), torch.zeros(1, 1, 9, 8), torch.eye(3)[None])
    with pytest.raises(Exception, match="one pair"):
        vo.step(torch.zeros(2, 2, 8, 8), torch.zeros(2, 2, 8, 8), torch.zeros(2, 1, 8, 8), torch.eye(3)[None])


@pytest.mark.slow
def test_full_drive_with_iterative_scale():
    w, ff, fb, d = sequence("drive", 100)
    res = VisualOdometry(make_cfg(scale_method="iterative")).run(ff, fb, d, w.intrinsics(), batch_size=8)
    names = w.segment_names()
    err = rpe(w.poses(), res)
    static = torch.tensor([names[k] != "moving_car" and names[k + 1] != "moving_car" for k in range(len(res))])
    # iterative scale stops at |ds| < 1e-3, and frames right after a moving-car or still segment start from a
    # stale motion model: near-exact almost everywhere, millimetres at worst
    assert err[static].median() < 1e-4
    assert (err[static] < 1e-3).float().mean() > 0.9
    assert err[static].max() < 2e-2


def test_two_view_scale_cancels_opposite_depth_scale_errors(drive):
    """Depth of frame i 20 % too far and of frame j 20 % too near: the paper's one-view scale makes every
    translation 1.2x too long; ``scale_depth_views=2`` takes the geometric mean of the two views' scales,
    sqrt(1.2 / 1.2) = 1, i.e. the true translation."""
    w, ff, fb, d = drive
    n = 3  # straight driving: the E-tracker takes these pairs
    d_next = torch.stack([w.render(k + 1)["depth"] for k in range(n)])
    K, P = w.intrinsics(), w.poses()
    true_len = torch.stack([(torch.linalg.inv(P[k]) @ P[k + 1])[:3, 3].norm() for k in range(n)])
    one = VisualOdometry(make_cfg(tracker="e")).run(ff[:n], fb[:n], 1.2 * d[:n], K, batch_size=n,
                                                         depths_next=d_next / 1.2)  # ignored with one view
    two = VisualOdometry(make_cfg(tracker="e", depth_views=2)).run(
        ff[:n], fb[:n], 1.2 * d[:n], K, batch_size=n, depths_next=d_next / 1.2)
    assert all(r.diagnostics.tracker == "E" for r in one + two)
    len_one = torch.stack([r.T_prev_cur[:3, 3].norm() for r in one])
    assert torch.allclose(len_one / true_len, torch.full((n,), 1.2, dtype=torch.float64), atol=2e-3)
    assert rpe(P, two).max() < 1e-3
    vo = VisualOdometry(make_cfg(tracker="e", depth_views=2))  # streaming gives the same
    stream = [vo.step(ff[k:k + 1], fb[k:k + 1], 1.2 * d[k:k + 1], K[None], depth_cur=d_next[k:k + 1] / 1.2)
              for k in range(n)]
    for a, b in zip(two, stream, strict=True):
        assert torch.allclose(a.T_w_cur, b.T_w_cur, atol=1e-9)


def test_two_view_scale_keeps_the_earlier_view_when_the_views_disagree(drive):
    """The later depth half of the truth (its scale 2x off, beyond scale_views_max_ratio=1.5): not averaged, the
    earlier frame's exact scale is used."""
    w, ff, fb, d = drive
    n = 2
    d_next = torch.stack([w.render(k + 1)["depth"] for k in range(n)])
    res = VisualOdometry(make_cfg(tracker="e", depth_views=2)).run(
        ff[:n], fb[:n], d[:n], w.intrinsics(), batch_size=n, depths_next=d_next / 2)
    assert all(r.diagnostics.tracker == "E" for r in res)
    assert rpe(w.poses(), res).max() < 1e-3
    with pytest.raises(ValueError, match="views_max_ratio"):
        make_cfg(views_max_ratio=1.0)


def test_two_view_scale_uses_the_later_view_alone_when_the_earlier_fails(drive):
    """No usable depth in frame i (all zero): the one-view scale fails (tracker=e falls back to constant motion);
    with two views the later frame's true depth alone gives the exact translation."""
    w, ff, fb, d = drive
    n = 2
    d_next = torch.stack([w.render(k + 1)["depth"] for k in range(n)])
    zero = torch.zeros_like(d[:n])
    one = VisualOdometry(make_cfg(tracker="e")).run(ff[:n], fb[:n], zero, w.intrinsics(), batch_size=n)
    assert all(r.diagnostics.tracker == "constant_motion" for r in one)
    two = VisualOdometry(make_cfg(tracker="e", depth_views=2)).run(
        ff[:n], fb[:n], zero, w.intrinsics(), batch_size=n, depths_next=d_next)
    assert all(r.diagnostics.tracker == "E" for r in two)
    assert rpe(w.poses(), two).max() < 1e-3


def test_two_view_scale_needs_the_later_depth(drive):
    w, ff, fb, d = drive
    with pytest.raises(ValueError, match="depth_views=2"):
        VisualOdometry(make_cfg(depth_views=2)).run(ff[:2], fb[:2], d[:2], w.intrinsics())
    with pytest.raises(ValueError, match="depth_views"):
        make_cfg(depth_views=3)


def test_min_texture_keeps_only_textured_correspondences_and_needs_the_frames(drive):
    """tracker.correspondence.min_texture: every correspondence the tracker used scores at least the threshold in
    its frame (the Shi-Tomasi score of the frame given), fewer than without it, and the oracle pose stays exact;
    without the frames the tracker warns once and selects as without the test."""
    from dataclasses import replace

    from dfvo.matching.image_ops import shi_tomasi

    w, ff, fb, d = drive
    K = w.intrinsics()
    imgs = torch.stack([w.render(i)["image"] for i in range(2)])
    cfg = make_cfg()
    gated_cfg = replace(cfg, correspondence=replace(cfg.correspondence, min_texture=1e-4))
    plain = VisualOdometry(cfg).step(ff[:1], fb[:1], d[:1], K[None], image_prev=imgs[:1], image_cur=imgs[1:])
    gated = VisualOdometry(gated_cfg).step(ff[:1], fb[:1], d[:1], K[None], image_prev=imgs[:1], image_cur=imgs[1:])
    texture = shi_tomasi(imgs[:1], 11, 1.0)[0, 0]
    u, v = gated.matches.pts_prev.round().long().unbind(-1)
    assert float(texture[v, u].min()) >= 1e-4
    pu, pv = plain.matches.pts_prev.round().long().unbind(-1)
    assert float(texture[pv, pu].min()) < 1e-4 and len(u) < len(pu)
    T = torch.linalg.inv(w.poses()[0]) @ w.poses()[1]
    assert float((gated.T_prev_cur[:3, 3] - T[:3, 3]).norm()) < 1e-3
    vo = VisualOdometry(gated_cfg)
    with pytest.warns(UserWarning, match="min_texture=0.0001 needs the frames"):
        blind = vo.step(ff[:1], fb[:1], d[:1], K[None])
    same = VisualOdometry(cfg).step(ff[:1], fb[:1], d[:1], K[None])
    assert torch.equal(blind.matches.pts_prev, same.matches.pts_prev)


def test_a_pair_failing_the_selection_is_tracked_under_the_first_relaxed_bound_that_passes(drive):
    """Exact forward flow, backward flow 0.3 px off everywhere (every pixel ~0.3 px inconsistent): at the official
    0.1 px the selection fails (constant motion); with relaxed_inconsistency=[0.2, 0.4, 0.8] the pair is selected
    under 0.4 (0.2 still fails), flagged, and E recovers the true step; the rows of the other pair of the batch,
    which passes at 0.1, are untouched. A relaxed list must climb above max_inconsistency."""
    from dataclasses import replace

    from dfvo.matching.selection import SelectionConfig

    w, ff, fb, d = drive
    K = w.intrinsics()
    fb_off = fb[:2].clone()
    fb_off[0, 0] += 0.3
    cfg = make_cfg()
    assert cfg.correspondence.relaxed_inconsistency == [0.2, 0.4, 0.8]  # the default
    cfg = replace(cfg, correspondence=replace(cfg.correspondence, relaxed_inconsistency=[]))  # the paper's rule
    plain = VisualOdometry(cfg).run(ff[:2], fb_off, d[:2], K, batch_size=2)
    assert plain[0].diagnostics.selection_failed and plain[0].diagnostics.constant_motion
    relaxed_cfg = replace(cfg, correspondence=replace(cfg.correspondence, relaxed_inconsistency=[0.2, 0.4, 0.8]))
    res = VisualOdometry(relaxed_cfg).run(ff[:2], fb_off, d[:2], K, batch_size=2)
    first = res[0].diagnostics
    assert not first.selection_failed and first.selection_max_inconsistency == 0.4 and first.tracker == "E"
    T = torch.linalg.inv(w.poses()[0]) @ w.poses()[1]
    assert float((res[0].T_prev_cur[:3, 3] - T[:3, 3]).norm()) < 1e-3
    assert res[1].diagnostics.selection_max_inconsistency is None
    assert torch.equal(res[1].matches.pts_prev, plain[1].matches.pts_prev)
    with pytest.raises(ValueError, match="relaxed_inconsistency"):
        SelectionConfig(relaxed_inconsistency=[0.5, 0.2])
    with pytest.raises(ValueError, match="relaxed_inconsistency"):
        SelectionConfig(relaxed_inconsistency=[0.05])
