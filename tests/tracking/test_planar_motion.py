"""Planar scenes tracked by the homography's decomposition (``tracker.model_selection.planar=homography``)."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.synthetic import SyntheticWorld
from dfvo.tracking.config import CameraHeightConfig, ModelSelectionConfig, ScaleConfig, TrackerConfig
from dfvo.tracking.odometry import VisualOdometry

N = 12


@pytest.fixture(scope="module")
def planar_world() -> tuple:
    """The synthetic planar scene (only the road plane in view), exact flow, the true depth times a random factor
    per frame (exp(0.3 N(0,1)): a network whose metric scale is unreliable from frame to frame, as the
    driving-trained depth is indoors), and the true steps."""
    w = SyntheticWorld(seed=1000, num_frames=N + 1, scenario="planar", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(N)]
    ff, fb = torch.stack([f["flow_fwd"] for f in frames]), torch.stack([f["flow_bwd"] for f in frames])
    depth = torch.stack([f["depth"] for f in frames])
    noisy = depth * torch.exp(0.3 * torch.randn(N, 1, 1, 1, generator=torch.Generator().manual_seed(1)))
    P = w.poses().to(torch.float64)
    return ff, fb, noisy, w.intrinsics(), (torch.linalg.inv(P[:-1]) @ P[1:])[:N]


def _run(planar: str, world: tuple) -> tuple[list, torch.Tensor, torch.Tensor]:
    ff, fb, depth, K, true = world
    cfg = TrackerConfig(scale=ScaleConfig(depth_views=1), camera_height=CameraHeightConfig(estimate=False),
                        model_selection=ModelSelectionConfig(planar=planar), motion="car")  # the setting as given
    res = VisualOdometry(cfg).run(ff, fb, depth, K, batch_size=4)
    steps = torch.stack([r.T_prev_cur for r in res])
    direction = torch.rad2deg(torch.arccos((torch.nn.functional.normalize(steps[:, :3, 3], dim=-1)
                                            * torch.nn.functional.normalize(true[:, :3, 3], dim=-1)).sum(-1)
                                           .clamp(-1, 1)))
    ratio = steps[:, :3, 3].norm(dim=-1) / true[:, :3, 3].norm(dim=-1)
    return res, direction, ratio


def test_a_plane_is_tracked_by_its_homography_with_steady_lengths(planar_world: tuple) -> None:
    """On a plane GRIC prefers H on every pair. The paper's PnP takes each step's length from that frame's depth, so
    the lengths jump with the depth's per-frame scale (frame-to-frame log ratio spread ~0.3); the homography's
    decomposition gives the true directions (the plane in front of the camera that best explains the CNN depth's
    shape) and its lengths come through the scale filter, whose three-frame relative scale carries
    them smoothly (spread < a third of PnP's) towards the truth."""
    res_pnp, _, ratio_pnp = _run("pnp", planar_world)
    res_h, direction, ratio_h = _run("homography", planar_world)
    assert all(str(r.diagnostics.tracker) == "PnP" for r in res_pnp)
    assert all(str(r.diagnostics.tracker) == "E" and r.diagnostics.homography_motion for r in res_h)
    assert float(direction.max()) < 0.1, direction
    rot = [math.degrees(math.acos(min(1.0, (float((r.T_prev_cur[:3, :3] @ t[:3, :3].T).trace()) - 1) / 2)))
           for r, t in zip(res_h, planar_world[4])]
    assert len(rot) == N and max(rot) < 0.05, rot
    jumps_pnp = ratio_pnp.log().diff().std()
    jumps_h = ratio_h.log().diff().std()
    assert float(jumps_h) < float(jumps_pnp) / 3, (ratio_h, ratio_pnp)
    assert abs(float(ratio_h[-3:].mean()) - 1) < 0.05, ratio_h  # the filter has converged to the true length


def test_planar_homography_streams_as_it_runs(planar_world: tuple) -> None:
    """The homography path keeps per-frame state (the last plane): frame-by-frame ``step`` and batched ``run`` (two
    batch sizes) give the same poses."""
    ff, fb, depth, K, _ = planar_world
    cfg = TrackerConfig(scale=ScaleConfig(depth_views=1), camera_height=CameraHeightConfig(estimate=False),
                        model_selection=ModelSelectionConfig(planar="homography"), motion="car")
    runs = [torch.stack([r.T_w_cur for r in VisualOdometry(cfg).run(ff, fb, depth, K, batch_size=b)]) for b in (4, 3)]
    vo = VisualOdometry(cfg)
    streamed = torch.stack([vo.step(ff[k:k + 1], fb[k:k + 1], depth[k:k + 1], K[None]).T_w_cur for k in range(N)])
    assert torch.allclose(runs[0], runs[1], atol=1e-9) and torch.allclose(runs[0], streamed, atol=1e-9)


def test_planar_homography_needs_gric() -> None:
    """planar=homography with the flow-magnitude rule (no homography fitted): one line naming both settings."""
    with pytest.raises(ValueError, match="tracker.model_selection.planar=homography needs method=gric"):
        ModelSelectionConfig(method="flow", planar="homography")


def test_a_homography_decomposed_on_demand_equals_the_batchs(planar_world: tuple,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """A pair whose motion turned hand-held after its batch was tracked (``tracker.motion=auto``'s revision) has its
    homography decomposed when it needs it (``ETrackerResult.with_homography``): with the batched decomposition
    withheld from every batch the planar world's poses are those of the batched path, and every frame still takes
    the homography's motion."""
    from dfvo.tracking.motion_model import MotionJudge

    ff, fb, depth, K, _ = planar_world
    cfg = TrackerConfig(scale=ScaleConfig(depth_views=1), camera_height=CameraHeightConfig(estimate=False),
                        motion="handheld")
    batched = VisualOdometry(cfg).run(ff, fb, depth, K, batch_size=4)
    monkeypatch.setattr(MotionJudge, "may_use_homography", property(lambda self: False))
    on_demand = VisualOdometry(cfg).run(ff, fb, depth, K, batch_size=4)
    assert all(r.diagnostics.homography_motion for r in on_demand)
    for a, b in zip(batched, on_demand):
        assert torch.allclose(a.T_w_cur, b.T_w_cur, atol=1e-9)
