"""The inference loop: its overlap modes (serial; loader thread; loader and tracker threads) give the same poses for
any batch size (``full`` splitting the refinement between its two threads; ``auto``: full with two torch threads or on
CUDA); frames are decoded once each, in the background unless serial; refinement is applied to the
network-like flow; an early stop or a tracker error leaves no thread behind; an unknown mode is one clear error;
``overlap=`` and ``cuda_sync=`` are settings of infer.py that reach the loop and its stage timer."""

from __future__ import annotations

import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import dfvo.inference.refine_split as refine_split
from dfvo.inference.config import OverlapMode
from dfvo.inference.frames import FrameSequence
from dfvo.inference.loop import resolve_overlap, track_sequence
from dfvo.inference.timing import StageTimer
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_consecutive
from dfvo.synthetic import SyntheticWorld
from dfvo.tracking import VisualOdometry

H, W, N = 64, 224, 9


class _CachedSources:
    """Flow (true flow + a smooth 1 px perturbation, like a network's) and true depth of a synthetic world,
    rendered once; it reads no images, so the sequence it serves needs no world."""

    name = "network"

    def __init__(self, world: SyntheticWorld) -> None:
        g = torch.Generator().manual_seed(0)
        noise = [F.interpolate(torch.randn(1, 2, 4, 12, generator=g), size=(H, W), mode="bilinear")[0]
                 for _ in range(2 * N)]
        self.fwd = {i: world.flow(i, i + 1)[0] + noise[2 * i] for i in range(N - 1)}
        self.bwd = {i: world.flow(i + 1, i)[0] + noise[2 * i + 1] for i in range(N - 1)}
        self.depth = {i: world.depth(i) for i in range(N)}
        self.flow_calls: list[list[int]] = []

    def __call__(self, prev: torch.Tensor, cur: torch.Tensor, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        self.flow_calls.append(list(indices))
        return torch.stack([self.fwd[i] for i in indices]), torch.stack([self.bwd[i] for i in indices])

    def depth_source(self) -> object:
        src = self

        class _Depth:
            name = "oracle"

            def __call__(self, images: torch.Tensor, indices: list[int]) -> torch.Tensor:
                return torch.stack([src.depth[i] for i in indices])

        return _Depth()


@pytest.fixture(scope="module")
def world_data() -> tuple[FrameSequence, _CachedSources]:
    world = SyntheticWorld(seed=2, num_frames=N, height=H, width=W, scenario="drive")
    images = [world.image(i) for i in range(N)]
    seq = FrameSequence("loop_test", N, world.intrinsics().float(), lambda i: images[i].clone(),
                        world.poses().numpy())
    return seq, _CachedSources(world)


def _run(seq: FrameSequence, src: _CachedSources, batch: int, overlap: str | bool, refine: FlowRefinementConfig | None,
         timer: StageTimer | None = None) -> list:
    return list(track_sequence(seq, src, src.depth_source(), VisualOdometry(), refine=refine, batch_size=batch,
                               timer=timer or StageTimer(), overlap=overlap))


def _dfvo_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("dfvo-") and t.is_alive()]


def test_overlap_and_batch_size_do_not_change_the_poses(world_data: tuple) -> None:
    seq, src = world_data
    refine = FlowRefinementConfig()
    timer = StageTimer()
    ref = _run(seq, src, 1, "none", refine)
    assert [r.index for r in ref] == list(range(1, N))
    for batch, overlap in ((1, "full"), (3, "full"), (4, False), (8, "load"), (2, True)):
        out = _run(seq, src, batch, overlap, refine, timer if batch == 3 else None)
        assert [r.index for r in out] == list(range(1, N))
        for a, b in zip(ref, out, strict=True):
            torch.testing.assert_close(b.result.T_w_cur, a.result.T_w_cur, atol=1e-9, rtol=0)
            assert b.result.diagnostics.tracker == a.result.diagnostics.tracker
            assert b.result.diagnostics.num_inliers == a.result.diagnostics.num_inliers
    # the tracker worked on the refined flows: every frame tracked (no constant motion), the path's length that of
    # the truth (oracle depth: 5 %) and its end near the truth's. The end's error is 6-12 % of the distance depending
    # on the CPU's kernels (ATEN_CPU_CAPABILITY=default: 11.6 %; 8 pairs of 64x224 frames with 1 px flow noise), so
    # it is bounded at 20 %: a tracker on unrefined flows falls back to constant motion and fails the first check.
    assert all(r.result.diagnostics.tracker.value in ("E", "PnP") for r in ref)
    true = torch.from_numpy(np.linalg.inv(seq.poses[0]) @ seq.poses[-1])
    positions = torch.stack([torch.zeros(3, dtype=torch.float64)] + [r.result.T_w_cur[:3, 3] for r in ref])
    true_positions = torch.from_numpy(np.stack([(np.linalg.inv(seq.poses[0]) @ p)[:3, 3] for p in seq.poses]))
    length, true_length = (positions.diff(dim=0).norm(dim=1).sum(), true_positions.diff(dim=0).norm(dim=1).sum())
    assert abs(float(length / true_length) - 1) < 0.05, (float(length), float(true_length))
    assert float((ref[-1].result.T_w_cur[:3, 3] - true[:3, 3]).norm()) < 0.2 * float(true[:3, 3].norm())
    assert {"load", "flow", "refine", "depth", "tracker", "wait_load", "wait_tracker"} <= set(timer.total)
    assert all(r.stage_seconds["t_tracker"] > 0 for r in out)


def test_the_tracker_gets_the_refined_flows(world_data: tuple) -> None:
    seq, src = world_data
    refine = FlowRefinementConfig()
    out = _run(seq, src, 4, True, refine)
    images = torch.stack([seq.image(i) for i in range(5)])
    fwd, bwd = refine_consecutive(images, torch.stack([src.fwd[i] for i in range(4)]),
                                  torch.stack([src.bwd[i] for i in range(4)]), refine)
    torch.testing.assert_close(torch.stack([r.flow_fwd for r in out[:4]]), fwd)
    torch.testing.assert_close(torch.stack([r.flow_bwd for r in out[:4]]), bwd)
    unrefined = _run(seq, src, 4, True, None)
    assert torch.equal(unrefined[0].flow_fwd, src.fwd[0])
    # a 1 px error passes the 0.1 px forward-backward test nowhere: unrefined, the selection fails at 0.1 px (and
    # falls back to constant motion or to a relaxed bound, tracker.correspondence.relaxed_inconsistency)
    def at_official_bound(r: object) -> bool:
        d = r.result.diagnostics
        return not d.selection_failed and d.selection_max_inconsistency is None

    assert not any(at_official_bound(r) for r in unrefined)
    assert all(at_official_bound(r) for r in out)
    assert out[0].stage_seconds["t_refine"] > 0 and unrefined[0].stage_seconds["t_refine"] == 0


def test_frames_are_decoded_once_each_in_the_loader_thread(world_data: tuple) -> None:
    seq, src = world_data
    calls: list[tuple[int, str]] = []

    def load(i: int) -> torch.Tensor:
        calls.append((i, threading.current_thread().name))
        return seq.load(i)

    for mode in ("load", "full"):
        calls.clear()
        timer = StageTimer()
        _run(replace(seq, load=load), src, 3, mode, None, timer)
        assert sorted(i for i, _ in calls) == list(range(N))
        assert all(name.startswith("dfvo-load") for _, name in calls)
        assert ("wait_tracker" in timer.total) == (mode == "full")
    calls.clear()
    _run(replace(seq, load=load), src, 3, "none", None)
    assert sorted(i for i, _ in calls) == list(range(N))
    assert all(name == threading.current_thread().name for _, name in calls)


def test_early_stop_and_tracker_errors_leave_no_thread(world_data: tuple) -> None:
    seq, src = world_data
    threads = torch.get_num_threads()
    gen = track_sequence(seq, src, src.depth_source(), VisualOdometry(), refine=None, batch_size=2,
                         timer=StageTimer(), overlap=True)
    first = next(gen)
    assert first.index == 1 and _dfvo_threads()
    gen.close()
    assert not _dfvo_threads()
    assert torch.get_num_threads() == threads  # "full" halves the torch threads during the loop only

    class Broken(VisualOdometry):
        def run(self, *args: object, **kwargs: object) -> list:
            raise RuntimeError("tracker exploded")

    with pytest.raises(RuntimeError, match="tracker exploded"):
        list(track_sequence(seq, src, src.depth_source(), Broken(), refine=None, batch_size=2, timer=StageTimer(),
                            overlap=True))
    assert not _dfvo_threads()


def test_an_unknown_overlap_mode_is_one_clear_error(world_data: tuple) -> None:
    seq, src = world_data
    with pytest.raises(ValueError, match=r"overlap='both'; expected one of \['none', 'load', 'full', 'auto'\]"):
        _run(seq, src, 2, "both", None)
    assert not _dfvo_threads()


def test_overlap_and_cuda_sync_are_infer_settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``overlap=`` and ``cuda_sync=`` on infer.py's command line reach the loop and the stage timer (no module
    switch to set from outside), and the run's poses do not depend on the mode."""
    from hydra import compose, initialize_config_module

    import dfvo.inference.pipeline as pipeline

    seen: list[tuple[str, bool]] = []
    real = pipeline.track_sequence

    def spy(*args: object, **kwargs: object) -> object:
        seen.append((kwargs["overlap"], kwargs["timer"].cuda_sync))
        yield from real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "track_sequence", spy)
    poses = {}
    for overlap, sync in (("none", "true"), ("full", "false")):
        with initialize_config_module("dfvo.conf.infer", version_base="1.3"):
            cfg = compose("infer", overrides=["data.num_frames=4", "img_res.height=64", "img_res.width=96",
                                              "flow=oracle", "depth=oracle", "progress=false", "batch_size=2",
                                              f"out_dir={tmp_path / overlap}", f"overlap={overlap}",
                                              f"cuda_sync={sync}"])
        summary = pipeline.run_inference(cfg)
        poses[overlap] = np.loadtxt(summary["pose_file"])
    assert seen == [(OverlapMode.none, True), (OverlapMode.full, False)]
    assert poses["none"].shape == (4, 12) and np.array_equal(poses["none"], poses["full"])
    for overlap in ("none", "full"):
        assert json.loads((tmp_path / overlap / "summary.json").read_text())["overlap"] == overlap


def test_auto_overlap_is_full_with_two_torch_threads_or_cuda_else_load() -> None:
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert resolve_overlap("auto") == OverlapMode.full
        torch.set_num_threads(1)
        assert resolve_overlap("auto") == OverlapMode.load
        assert resolve_overlap("auto", "cuda:0") == OverlapMode.full
        assert resolve_overlap("none") == OverlapMode.none and resolve_overlap(True) == OverlapMode.full
    finally:
        torch.set_num_threads(threads)


def test_full_overlap_splits_the_refinement_between_the_two_threads(world_data: tuple,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``overlap="full"`` the first batch's dense refinement runs after the networks in the main thread and its
    pyramid refinement in the tracker thread (later batches wherever the balance puts the cut); the flows the tracker
    gets are those of one ``dense_pyramid`` call; the timer keeps the cut of every batch."""
    seq, src = world_data
    calls: list[tuple[str, str, int]] = []
    real = refine_split.refine_consecutive

    def spy(images: torch.Tensor, fwd: torch.Tensor, bwd: torch.Tensor, cfg: FlowRefinementConfig):
        calls.append((threading.current_thread().name, cfg.mode.value, fwd.shape[0]))
        return real(images, fwd, bwd, cfg)

    monkeypatch.setattr(refine_split, "refine_consecutive", spy)
    timer = StageTimer()
    out = _run(seq, src, 3, "full", FlowRefinementConfig(), timer)
    batches = -(-(N - 1) // 3)
    main = threading.current_thread().name
    assert [c for c in calls if c[0] == main][0] == (main, "dense", 3)
    assert [c[1:] for c in calls if c[0].startswith("dfvo-track")][0] == ("pyramid", 3)
    assert sum(n for _, mode, n in calls if mode == "dense") == N - 1  # each pair refined once by each stage
    assert sum(n for _, mode, n in calls if mode == "pyramid") == N - 1
    assert timer.refine_cut["units_per_batch"] == 6 and len(timer.refine_cut["network_thread_units"]) == batches
    assert timer.refine_cut["network_thread_units"][0] == 3
    images = torch.stack([seq.image(i) for i in range(N)])
    fwd, bwd = real(images, torch.stack([src.fwd[i] for i in range(N - 1)]),
                    torch.stack([src.bwd[i] for i in range(N - 1)]), FlowRefinementConfig())
    assert torch.equal(torch.stack([r.flow_fwd for r in out]), fwd)
    assert torch.equal(torch.stack([r.flow_bwd for r in out]), bwd)
    assert all(r.stage_seconds["t_refine"] > 0 for r in out)
