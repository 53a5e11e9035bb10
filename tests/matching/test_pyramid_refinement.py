"""Coarse-to-fine sparse flow refinement: recovers shifts far beyond one level's reach, brings a perturbed true flow of
the synthetic world to the renderer's accuracy (as OpenCV's pyramidal LK does from the same start), writes forward
and backward flows so that the forward-backward test reads them exactly, and leaves every other pixel alone."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.pyramid_refinement import (
    PyramidRefinementConfig,
    build_pyramid,
    lucas_kanade,
    refine_pairs_pyramid,
    refine_pyramid,
    select_candidates,
)
from dfvo.synthetic import SyntheticWorld

H, W = 192, 320


def _texture(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """A smooth pattern in [0,1] (incommensurate sinusoids), evaluated exactly at any real (u, v)."""
    t = torch.zeros_like(u)
    for a, fu, fv, ph in ((0.20, 0.21, 0.05, 0.3), (0.15, -0.07, 0.23, 1.1), (0.10, 0.31, -0.17, 2.0),
                          (0.05, 0.11, 0.13, 0.7), (0.10, 0.37, 0.29, 0.2)):
        t = t + a * torch.sin(fu * u + fv * v + ph)
    return 0.5 + t


def _shifted_frames(shift: tuple[float, float]) -> torch.Tensor:
    """(2,3,H,W): frame 1 is frame 0 moved by ``shift`` (the point at x in frame 0 is at x + shift in frame 1)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    frames = torch.stack([_texture(u, v), _texture(u - shift[0], v - shift[1])]).float()
    return frames[:, None].expand(2, 3, H, W).contiguous()


def _refined(before: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    return (before != after).any(1)


def _zoom_frames(scale: float, degrees: float, shift: tuple[float, float]) -> tuple[torch.Tensor, ...]:
    """A forward-driving-like motion with exact flows: frame 1 is frame 0 zoomed by ``scale`` and rotated by
    ``degrees`` about the image centre, then moved by ``shift`` (the point at p in frame 0 is at
    c + s R (p - c) + t in frame 1). Returns (2,3,H,W) frames and the true (1,2,H,W) forward and backward flows."""
    a = math.radians(degrees)
    A = scale * torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    c = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=torch.float64)
    t = torch.tensor(shift, dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    p = torch.stack([u, v], -1)
    to_1 = (p - c) @ A.T + c + t  # where each pixel of frame 0 goes
    from_0 = (p - c - t) @ torch.linalg.inv(A).T + c  # where each pixel of frame 1 comes from
    frames = torch.stack([_texture(u, v), _texture(from_0[..., 0], from_0[..., 1])]).float()
    frames = frames[:, None].expand(2, 3, H, W).contiguous()
    return frames, (to_1 - p).permute(2, 0, 1)[None].float(), (from_0 - p).permute(2, 0, 1)[None].float()


def test_network_like_error_of_ten_pixels_is_pulled_back_to_the_exact_flow() -> None:
    """Exact truth (analytic texture, zoom + rotation + shift): a start ~11 px off the true flow (a smooth offset
    plus noise, as a network trained on slower motion errs) is refined to < 0.1 px at most textured candidates
    that pass the 0.1 px forward-backward test; the same refinement at one level cannot (it lands < 15 % as many)."""
    frames, gt_f, gt_b = _zoom_frames(1.01, 0.3, (3.0, -1.5))
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    gen = torch.Generator().manual_seed(0)
    error = torch.stack([9.0 + torch.sin(u / 37 + v / 23), -6.0 + torch.cos(u / 29 - v / 41)])[None]
    start_f = gt_f + error + 0.3 * torch.randn(1, 2, H, W, generator=gen)
    start_b = gt_b - error + 0.3 * torch.randn(1, 2, H, W, generator=gen)
    assert float((start_f - gt_f).norm(dim=1).min()) > 8.0  # far beyond one level's reach (~window/2)

    def landed(cfg: PyramidRefinementConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        fwd, bwd = refine_pyramid(frames, start_f, start_b, cfg)
        consistent = _refined(start_f, fwd)[0] & (forward_backward_inconsistency(fwd, bwd)[0, 0] < 0.1)
        return consistent, (fwd - gt_f).norm(dim=1)[0], (bwd - gt_b).norm(dim=1)[0][_refined(start_b, bwd)[0]]

    consistent, err, err_b = landed(PyramidRefinementConfig(sigma=0.0))
    assert int(consistent.sum()) > 2000
    assert float(err[consistent].median()) < 0.06
    assert float((err[consistent] < 0.1).float().mean()) > 0.85
    assert float(err_b.median()) < 0.06
    one, err_one, _ = landed(PyramidRefinementConfig(levels=1, iterations=[9], sigma=0.0))
    assert int((one & (err_one < 0.1)).sum()) < 0.15 * int((consistent & (err < 0.1)).sum())


@pytest.mark.parametrize("shift, beyond_one_level", [((6.3, 2.9), False), ((-11.6, 4.4), True)])
def test_recovers_a_shift_one_level_cannot(shift: tuple[float, float], beyond_one_level: bool) -> None:
    """From zero flow: three levels recover a 7-12 px shift to a few hundredths of a pixel at the points that pass
    the forward-backward test (most of them); one level does not."""
    frames = _shifted_frames(shift)
    zero = torch.zeros(1, 2, H, W)
    truth = torch.tensor(shift).view(1, 2, 1, 1)
    fwd, bwd = refine_pyramid(frames, zero, zero, PyramidRefinementConfig(levels=3, sigma=0.0))
    moved = _refined(zero, fwd)[0]
    assert int(moved.sum()) > 1000
    consistent = moved & (forward_backward_inconsistency(fwd, bwd)[0, 0] < 0.1)
    assert int(consistent.sum()) > 0.8 * int(moved.sum())
    err = (fwd - truth).norm(dim=1)[0][consistent]
    assert float(err.median()) < 0.05
    assert float((err < 0.2).float().mean()) > 0.95
    err_b = (bwd + truth).norm(dim=1)[0][_refined(zero, bwd)[0]]
    assert float(err_b.median()) < 0.06
    if beyond_one_level:
        single, single_b = refine_pyramid(frames, zero, zero,
                                          PyramidRefinementConfig(levels=1, iterations=[9], sigma=0.0))
        one = _refined(zero, single)[0] & (forward_backward_inconsistency(single, single_b)[0, 0] < 0.1)
        right = one & ((single - truth).norm(dim=1)[0] < 0.2)
        assert int(right.sum()) < 0.2 * int(consistent.sum())


def test_written_flows_pass_the_forward_backward_test_exactly() -> None:
    """The backward flow is written at the four pixels around each refined target, so the bilinear
    forward-backward test of dfvo.matching.consistency reads the refined backward flow itself."""
    frames = _shifted_frames((3.4, -1.7))
    zero = torch.zeros(1, 2, H, W)
    fwd, bwd = refine_pyramid(frames, zero, zero, PyramidRefinementConfig(sigma=0.0))
    moved = _refined(zero, fwd)[0]
    incon = forward_backward_inconsistency(fwd, bwd)[0, 0][moved]
    assert float((incon < 0.1).float().mean()) > 0.9
    untouched = ~moved
    assert bool((fwd[0][:, untouched] == 0).all())  # every other pixel keeps its input flow


def test_synthetic_world_from_a_network_like_error_matches_opencv() -> None:
    """A true flow of the synthetic world off by 5 px (plus noise) at the candidates: the consistent refined ones
    reach the accuracy of the renderer's texture (~0.2 px), like OpenCV's pyramidal LK from the same start."""
    cv2 = pytest.importorskip("cv2")
    import numpy as np

    world = SyntheticWorld(seed=7, num_frames=3, height=H, width=W, scenario="city")
    frames = torch.stack([world.image(1), world.image(2)])
    gt_f, valid = world.flow(1, 2)
    gt_b, _ = world.flow(2, 1)
    gen = torch.Generator().manual_seed(0)
    offset = torch.tensor([4.0, -3.0]).view(1, 2, 1, 1)
    start_f = gt_f[None] + offset + 0.5 * torch.randn(1, 2, H, W, generator=gen)
    start_b = gt_b[None] - offset + 0.5 * torch.randn(1, 2, H, W, generator=gen)
    cfg = PyramidRefinementConfig()
    fwd, bwd = refine_pyramid(frames, start_f, start_b, cfg)
    incon = forward_backward_inconsistency(fwd, bwd)[0, 0]
    keep = _refined(start_f, fwd)[0] & (incon < 0.1) & valid[0]
    assert int(keep.sum()) > 300
    err = (fwd[0] - gt_f).norm(dim=0)[keep]
    assert float(err.median()) < 0.3
    assert float((err > 1.0).float().mean()) < 0.05
    # OpenCV's pyramidal Lucas-Kanade (3 levels, 7x7) from the same initial flow at the same pixels
    grey = (frames * torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1).mul(255).round().byte().numpy()
    vv, uu = torch.nonzero(keep, as_tuple=True)
    pts = torch.stack([uu, vv], -1).float()
    init = pts + start_f[0][:, vv, uu].T
    out, status, _ = cv2.calcOpticalFlowPyrLK(grey[0], grey[1], pts.numpy()[:, None], init.numpy()[:, None].copy(),
                                              winSize=(7, 7), maxLevel=2, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    ok = status[:, 0] == 1
    err_cv = np.linalg.norm(out[:, 0] - pts.numpy() - gt_f[:, vv, uu].T.numpy(), axis=1)[ok]
    assert float(err.median()) <= 1.25 * float(np.median(err_cv)) + 0.02


def test_pairs_entry_point_gives_the_consecutive_numbers() -> None:
    world = SyntheticWorld(seed=3, num_frames=3, height=96, width=320)
    frames = torch.stack([world.image(k) for k in range(3)])
    gen = torch.Generator().manual_seed(1)
    fwd = torch.stack([world.flow(k, k + 1)[0] for k in range(2)]) + torch.randn(2, 2, 96, 320, generator=gen)
    bwd = torch.stack([world.flow(k + 1, k)[0] for k in range(2)]) + torch.randn(2, 2, 96, 320, generator=gen)
    cfg = PyramidRefinementConfig(grid=[4, 8])
    a = refine_pyramid(frames, fwd, bwd, cfg)
    b = refine_pairs_pyramid(frames[:-1], frames[1:], fwd, bwd, cfg)
    for x, y in zip(a, b, strict=True):
        assert torch.allclose(x, y, atol=1e-5)


def test_candidates_are_spread_textured_and_inside() -> None:
    frames = _shifted_frames((0.0, 0.0))[:1]
    cfg = PyramidRefinementConfig(per_region=10, grid=[4, 5], cell=4)
    pts, mask = select_candidates(build_pyramid(frames, 1)[0], cfg)
    assert pts.shape == (1, 200, 2) and mask.shape == (1, 200)
    p = pts[0][mask[0]]
    assert len(p) > 150
    r = cfg.window // 2 + 1
    assert bool(((p[:, 0] >= r) & (p[:, 0] < W - r) & (p[:, 1] >= r) & (p[:, 1] < H - r)).all())
    cells = (p[:, 1] // 4) * 1000 + p[:, 0] // 4
    assert len(torch.unique(cells)) == len(p)  # at most one per cell
    flat = torch.full((1, 3, H, W), 0.5)
    _, mask_flat = select_candidates(build_pyramid(flat, 1)[0], cfg)
    assert not bool(mask_flat.any())  # no texture, no candidate


def test_flat_patches_and_non_finite_flows_are_left_alone() -> None:
    frames = _shifted_frames((1.0, 0.0))
    pyramid = build_pyramid(frames, 2)
    pts = torch.tensor([[[100.0, 50.0], [120.0, 60.0]]])
    flow = torch.tensor([[[float("nan"), 0.0], [0.0, 0.0]]])
    out, ok = lucas_kanade(pyramid, torch.tensor([0]), torch.tensor([1]), pts, flow, torch.ones(1, 2, dtype=torch.bool),
                           PyramidRefinementConfig(levels=2, iterations=[3, 3]))
    assert not bool(ok[0, 0]) and torch.isnan(out[0, 0, 0])
    assert bool(ok[0, 1]) and abs(float(out[0, 1, 0]) - 1.0) < 0.05


@pytest.mark.parametrize("bad, match", [({"window": 4}, "window=4"), ({"iterations": [3, 2]}, "iterations"),
                                        ({"backward_init": "zero"}, "backward_init"), ({"levels": 0}, "levels=0")])
def test_bad_settings_fail_with_one_line(bad: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        PyramidRefinementConfig(**bad)


def test_settings_are_a_structured_config_node() -> None:
    """The settings can sit in a Hydra config (e.g. ``flow.refine.pyramid``): command-line style overrides reach the
    object, and a bad value still fails with its one line when the node becomes the dataclass."""
    from omegaconf import OmegaConf

    node = OmegaConf.merge(OmegaConf.structured(PyramidRefinementConfig),
                           OmegaConf.from_dotlist(["levels=2", "iterations=[5,1]", "backward_init=forward"]))
    cfg = OmegaConf.to_object(node)
    assert isinstance(cfg, PyramidRefinementConfig)
    # backward_iterations unset stays None: the backward refinement runs ``iterations``
    assert (cfg.levels, cfg.iterations, cfg.backward_iterations, cfg.backward_init) == (2, [5, 1], None, "forward")
    bad = OmegaConf.merge(OmegaConf.structured(PyramidRefinementConfig), OmegaConf.from_dotlist(["levels=2"]))
    with pytest.raises(ValueError, match="iterations"):
        OmegaConf.to_object(bad)  # 3 counts for 2 levels


def test_levels_and_iterations_alone_override_infers_pyramid() -> None:
    """``flow.refine.pyramid.levels=2 flow.refine.pyramid.iterations=[3,2]`` on infer.py's command line is enough:
    the backward refinement follows ``iterations`` (it once kept the default's three counts and refused)."""
    from hydra import compose, initialize_config_module

    from dfvo.inference.config import typed

    with initialize_config_module("dfvo.conf.infer", version_base="1.3"):
        cfg = typed(compose("infer", overrides=["flow.refine.pyramid.levels=2",
                                                "flow.refine.pyramid.iterations=[3,2]"]))
    pyr = cfg.flow.refine.pyramid
    assert (pyr.levels, pyr.iterations, pyr.backward_iterations) == (2, [3, 2], None)
