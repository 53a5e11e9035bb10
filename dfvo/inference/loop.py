"""The inference loop: frames → flow and depth sources → :class:`dfvo.tracking.VisualOdometry`, one record per frame.

Convention:
    Flow and depth are computed for ``batch_size`` consecutive frame pairs at once (one network batch), and the
    tracker takes the same pairs as one batch (``VisualOdometry.run``). Network flow is refined photometrically
    (``refine``, :func:`dfvo.matching.flow_refinement.refine_consecutive`: each frame prepared once) before the
    forward-backward test; oracle and classical flows are used as they are. The depth given to the tracker is that
    of the earlier frame of each pair, in metres (with ``tracker.scale.depth_views=2`` also the later frame's);
    each frame's depth is computed once. Frame 0's pose is the identity and has no record.

Overlap (``overlap``, :class:`dfvo.inference.config.OverlapMode`; ``overlap=`` of ``infer.py``): ``"load"``
decodes and resizes the frames of batch k+1 in a loader thread while the main thread works on batch k (pinned for a
CUDA copy; not for the synthetic world, whose renderer the oracle sources share and whose caches are not
thread-safe: it renders in the main thread). ``"full"`` also moves the tracker to a tracker thread, which works on
batch k-1 while the main thread runs the flow and depth networks of batch k; the refinement is cut between them,
by pairs and stages, where the two threads' busy times even out (:mod:`dfvo.inference.refine_split`: the flows are
those of one refinement call, bit for bit, wherever the cut falls); on a CPU the two
busy threads then get half of the torch threads each (restored after the loop), so their OpenMP teams do not compete
for the same cores: on two cores, two single-threaded pipelines, which waste none of the time small tensor ops lose
to OpenMP's fork and join (docs/speed.md, "Overlap"). ``"auto"`` (the default) is ``"full"`` with two or more torch
threads or on CUDA, else ``"load"``. ``"none"`` is the serial loop: on a CPU shared with other processes it is much
slower than ``"load"`` (GNU OpenMP's workers busy-wait long after each parallel region unless the process has more
OpenMP threads than CPUs, as the loader thread makes it; measured in docs/speed.md, "Overlap"). The tracker's state is
sequential, so batches reach it one at a time and in order; each frame draws its random samples from its own seeded
generator, so the poses are the same, bit for bit, in every mode and for any batch size. Stage times of different
threads overlap (``load``, ``refine`` and ``tracker`` are measured in the thread that runs them; ``wait_load`` and
``wait_tracker`` are what the main thread spent blocked on them).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import torch

from dfvo.data.sequence import FrameSequence
from dfvo.inference.config import InferConfig, OverlapMode
from dfvo.inference.refine_split import RefineBalance, RefinePart, refine_stages, run_parts, whole_refinement
from dfvo.inference.timing import StageTimer
from dfvo.matching.flow_refinement import FlowRefinementConfig
from dfvo.sources.base import DepthSource, FlowSource
from dfvo.tracking import FrameResult, VisualOdometry
from dfvo.tracking.config import TrackerMode
from dfvo.validation import choice

__all__ = ["FrameRecord", "FrameStepper", "resolve_overlap", "track_sequence"]


def resolve_overlap(overlap: OverlapMode | str | bool, device: str = "cpu") -> OverlapMode:
    """The :class:`OverlapMode` the loop runs for an ``overlap`` argument (True: full; False: none; ``auto``:
    ``full`` on CUDA or with two or more torch threads, else ``load``)."""
    if isinstance(overlap, bool):
        return OverlapMode.full if overlap else OverlapMode.none
    mode = choice(OverlapMode, overlap, "overlap")
    if mode == OverlapMode.auto:
        cuda = torch.device(device).type == "cuda"
        return OverlapMode.full if cuda or torch.get_num_threads() >= 2 else OverlapMode.load
    return mode


@dataclass
class FrameRecord:
    """Everything known about one tracked frame ``index`` (the pair ``index-1 → index``).

    Attributes:
        image_prev, image: (3,H,W) frames ``index-1`` and ``index``. flow_fwd, flow_bwd: (2,H,W) the flows the
        tracker used. depth_prev: (1,H,W) metres. depth: (1,H,W) of frame ``index`` when it was computed (two-view
        scale), else None. result: the tracker's pose and diagnostics.
        stage_seconds: this frame's share of each stage (``t_flow``, ``t_refine``, ``t_depth``, ``t_tracker``).
        timestamp: the frame's time in seconds when the data has one (set by the run that writes the outputs).
    """

    index: int
    image_prev: torch.Tensor
    image: torch.Tensor
    flow_fwd: torch.Tensor
    flow_bwd: torch.Tensor
    depth_prev: torch.Tensor
    result: FrameResult
    stage_seconds: dict[str, float]
    depth: torch.Tensor | None = None
    timestamp: float | None = None


@dataclass
class _Batch:
    """One batch between the network stage and the tracker: pairs ``idx[k] → idx[k]+1``, (n+1,3,H,W) images."""

    idx: list[int]
    imgs: torch.Tensor
    flow_fwd: torch.Tensor
    flow_bwd: torch.Tensor
    depth: torch.Tensor
    depth_next: torch.Tensor | None
    share: dict[str, float]
    busy_main: float = 0.0  # seconds: the network thread's work on the batch (overlap="full")
    busy_tracker: float = 0.0  # seconds: the tracker thread's refinement and the tracker
    unit_seconds: dict[int, float] = field(default_factory=dict)  # per pair of each refinement stage that ran


class _Loader:
    """Frames of each batch, decoded in a background thread one batch ahead (or in the caller when disabled)."""

    def __init__(self, seq: FrameSequence, frames: list[list[int]], timer: StageTimer, background: bool,
                 pin: bool) -> None:
        self.seq, self.frames, self.timer, self.pin = seq, frames, timer, pin
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="dfvo-load") if background else None
        self.futures: dict[int, Future] = {}

    def _load(self, k: int) -> torch.Tensor:
        start, cpu, own = time.perf_counter(), time.process_time(), time.thread_time()
        out = torch.stack([self.seq.image(i) for i in self.frames[k]])
        if self.pin:
            out = out.pin_memory()
        self.timer.add("load", time.perf_counter() - start, time.process_time() - cpu, time.thread_time() - own)
        return out

    def _submit(self, k: int) -> None:
        if self.pool is not None and k < len(self.frames) and k not in self.futures:
            self.futures[k] = self.pool.submit(self._load, k)

    def get(self, k: int) -> torch.Tensor:
        """(n,3,H,W) CPU frames of batch ``k``; starts decoding batch ``k+1``."""
        if self.pool is None:
            return self._load(k)
        self._submit(k)
        self._submit(k + 1)
        with self.timer("wait_load"):
            return self.futures.pop(k).result()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)


def _batches(length: int, batch_size: int) -> list[list[int]]:
    batch = max(1, int(batch_size))
    return [list(range(first, min(first + batch, length - 1))) for first in range(0, length - 1, batch)]


def _two_views(vo: VisualOdometry) -> bool:
    """Whether the tracker takes the later frame's depth of each pair too (two-view scale)."""
    return vo.cfg.scale.depth_views == 2 and vo.cfg.mode != TrackerMode.pnp


def _pair_stage(imgs: torch.Tensor, idx: list[int], flow_src: FlowSource, depth_src: DepthSource, timer: StageTimer,
                two_views: bool, depth_carry: torch.Tensor | None, finetuner: object | None = None
                ) -> tuple[_Batch, torch.Tensor | None]:
    """Flow and depth of the pairs ``idx[k] -> idx[k]+1`` of ``imgs`` (n+1,3,H,W); ``depth_carry`` (1,1,H,W) is the
    first frame's depth when already computed (two-view scale). Returns the batch and the next carry."""
    n = len(idx)
    if finetuner is not None and finetuner.active:
        with timer("finetune"):
            for k in range(n):
                finetuner.step(*flow_src.network_inputs(imgs[k:k + 1], imgs[k + 1:k + 2]))
    with timer("flow") as flow_lap:
        flow_fwd, flow_bwd = flow_src(imgs[:-1], imgs[1:], idx)
    with timer("depth") as depth_lap:
        depth_next = None
        if two_views:
            later = depth_src(imgs[1:], [i + 1 for i in idx])
            first_depth = depth_src(imgs[:1], idx[:1]) if depth_carry is None else depth_carry
            depth = torch.cat([first_depth, later[:-1]])
            depth_next, depth_carry = later, later[-1:]
        else:
            depth = depth_src(imgs[:-1], idx)
    share = {"t_flow": flow_lap.seconds / n, "t_refine": 0.0, "t_depth": depth_lap.seconds / n, "t_tracker": 0.0}
    return _Batch(idx, imgs, flow_fwd, flow_bwd, depth, depth_next, share), depth_carry


def _refine_parts(work: _Batch, parts: list[RefinePart], timer: StageTimer) -> None:
    """Refine the pairs of ``parts`` of the batch photometrically in place (:func:`dfvo.inference.refine_split.
    run_parts`; all of them: :func:`~dfvo.inference.refine_split.whole_refinement`); adds the seconds to the batch's
    ``t_refine`` share and each stage's seconds per pair to ``unit_seconds``."""
    if not parts:
        return
    with timer("refine") as lap:
        work.flow_fwd, work.flow_bwd, per_pair = run_parts(parts, work.imgs, work.flow_fwd, work.flow_bwd)
    work.share["t_refine"] += lap.seconds / len(work.idx)
    work.unit_seconds.update(per_pair)


def _track_stage(work: _Batch, vo: VisualOdometry, K: torch.Tensor, timer: StageTimer) -> list[FrameResult]:
    """The tracker on the batch's pairs (K (1,3,3)), in order."""
    n = len(work.idx)
    with timer("tracker") as lap:
        results = vo.run(work.flow_fwd, work.flow_bwd, work.depth, K.expand(n, 3, 3), batch_size=n,
                         depths_next=work.depth_next, images=work.imgs)
    for part in ("selection", "e_tracker", "sequential"):  # the tracker's own split of its time
        timer.add(f"tracker_{part}", sum(getattr(r.diagnostics, f"time_{part}", 0.0) for r in results))
    work.share["t_tracker"] = lap.seconds / n
    return results


def _records(work: _Batch, results: list[FrameResult]) -> Iterator[FrameRecord]:
    for k, (i, res) in enumerate(zip(work.idx, results, strict=True)):
        yield FrameRecord(i + 1, work.imgs[k], work.imgs[k + 1], work.flow_fwd[k], work.flow_bwd[k], work.depth[k],
                          res, work.share, None if work.depth_next is None else work.depth_next[k])


class FrameStepper:
    """The loop of :func:`track_sequence` one frame at a time, for frames that arrive one by one (a live stream,
    :class:`dfvo.api.Odometry`): the same sources, refinement and tracker as a batch of one pair, each frame's depth
    computed once. Poses equal :func:`track_sequence`'s on the same frames (its batches are causal too).

    Args:
        flow_src, depth_src: the sources. vo: the odometry (its state continues). K: (3,3) working-size intrinsics.
        refine: photometric refinement of the flow (None: none). timer: stage times. device: where tensors live.
        finetuner: optional online flow finetuner.
    """

    def __init__(self, flow_src: FlowSource, depth_src: DepthSource, vo: VisualOdometry, K: torch.Tensor, *,
                 refine: FlowRefinementConfig | None, timer: StageTimer, device: str = "cpu",
                 finetuner: object | None = None) -> None:
        self.flow_src, self.depth_src, self.vo, self.stages = flow_src, depth_src, vo, refine_stages(refine)
        self.timer, self.device, self.finetuner = timer, device, finetuner
        self.K = K.to(device).reshape(1, 3, 3)
        self.reset()

    def reset(self) -> None:
        """Start a new sequence (the next frame is frame 0; the tracker forgets its state)."""
        self.vo.reset()
        self.index = -1
        self.prev: torch.Tensor | None = None
        self.depth_carry: torch.Tensor | None = None

    def push(self, image: torch.Tensor) -> FrameRecord | None:
        """Track frame ``image`` (3,H,W) float [0,1] at the working size: its :class:`FrameRecord` (None for the
        first frame, whose pose is the identity)."""
        img = image.to(self.device)[None]
        self.index += 1
        if self.prev is None:
            self.prev = img
            return None
        imgs = torch.cat([self.prev, img])
        self.prev = img
        work, self.depth_carry = _pair_stage(imgs, [self.index - 1], self.flow_src, self.depth_src, self.timer,
                                             _two_views(self.vo), self.depth_carry, self.finetuner)
        _refine_parts(work, whole_refinement(self.stages, 1), self.timer)
        return next(_records(work, _track_stage(work, self.vo, self.K, self.timer)))


def track_sequence(seq: FrameSequence, flow_src: FlowSource, depth_src: DepthSource, vo: VisualOdometry, *,
                   refine: FlowRefinementConfig | None, batch_size: int, timer: StageTimer, device: str = "cpu",
                   finetuner: object | None = None,
                   overlap: OverlapMode | str | bool = InferConfig.overlap) -> Iterator[FrameRecord]:
    """Track ``seq`` and yield one :class:`FrameRecord` per frame 1..N-1, in order, as soon as it is known.

    Args:
        seq: the frames. flow_src, depth_src: the sources. vo: the odometry (its state continues across calls).
        refine: photometric refinement of the flow (None: none). batch_size: frame pairs per batch.
        timer: receives ``load``, ``finetune``, ``flow``, ``refine``, ``depth``, ``tracker`` seconds (the tracker
            split into ``tracker_selection``, ``tracker_e_tracker``, ``tracker_sequential``; and ``wait_load``,
            ``wait_tracker`` when those run in background threads).
        device: where the frames, networks and tracker tensors live (``cpu``, ``cuda``, ``cuda:N``).
        finetuner: optional online flow finetuner (:class:`dfvo.training.online_flow.OnlineFlowFinetuner`).
        overlap: ``"none"``, ``"load"`` (decoding in a background thread), ``"full"`` (also the refinement and
            the tracker; see the module docstring) or ``"auto"`` (:func:`resolve_overlap`); True: ``"full"``,
            False: ``"none"``.
    """
    mode = resolve_overlap(overlap, device)
    K = seq.K.to(device)[None]
    two_views = _two_views(vo)
    batches = _batches(seq.length, batch_size)
    frames = [[i + 1 for i in idx] for idx in batches]
    frames[0] = [0] + frames[0]
    cuda = torch.device(device).type == "cuda"
    # the synthetic world's render caches are not thread-safe and its oracle sources use them in the main thread
    loader = _Loader(seq, frames, timer, background=mode != OverlapMode.none and seq.world is None,
                     pin=cuda and torch.cuda.is_available())
    tracker_pool = ThreadPoolExecutor(1, thread_name_prefix="dfvo-track") if mode == OverlapMode.full else None
    threads = torch.get_num_threads()
    if mode == OverlapMode.full and not cuda:  # two busy threads share the cores: half of the torch threads each
        torch.set_num_threads(max(1, threads // 2))

    # overlap="full": the refinement cut between the two threads where it evens them out (inference/refine_split.py)
    stages = refine_stages(refine)
    balance = RefineBalance(stages, batch_size) if mode == OverlapMode.full else None

    def track(work: _Batch, parts: list[RefinePart]) -> tuple[_Batch, list[FrameResult]]:
        start = time.perf_counter()
        _refine_parts(work, parts, timer)  # beside the next batch's networks
        results = _track_stage(work, vo, K, timer)
        work.busy_tracker = time.perf_counter() - start
        return work, results

    def collect(future: Future) -> tuple[_Batch, list[FrameResult]]:
        with timer("wait_tracker"):
            done, results = future.result()
        n = len(done.idx)
        balance.observe(done.busy_main / n, done.busy_tracker / n, done.unit_seconds)
        return done, results

    depth_carry: torch.Tensor | None = None  # depth of the first frame of the next batch (= this batch's last)
    prev_img: torch.Tensor | None = None
    pending: Future | None = None
    try:
        for b, idx in enumerate(batches):
            loaded = loader.get(b).to(device, non_blocking=True)
            imgs = loaded if prev_img is None else torch.cat([prev_img, loaded])
            prev_img = imgs[-1:]
            start = time.perf_counter()
            work, depth_carry = _pair_stage(imgs, idx, flow_src, depth_src, timer, two_views, depth_carry, finetuner)
            if tracker_pool is None:
                _refine_parts(work, whole_refinement(stages, len(idx)), timer)
                yield from _records(work, _track_stage(work, vo, K, timer))
                continue
            main_parts, tracker_parts = balance.parts(len(idx))
            _refine_parts(work, main_parts, timer)
            work.busy_main = time.perf_counter() - start  # networks (and online finetuning) and its refinement
            if pending is not None:
                done, pending = pending, None
                yield from _records(*collect(done))
            pending = tracker_pool.submit(track, work, tracker_parts)
        if pending is not None:
            done, pending = pending, None
            yield from _records(*collect(done))
    finally:
        loader.close()
        if tracker_pool is not None:
            tracker_pool.shutdown(wait=True, cancel_futures=True)
            if balance.total:  # a refinement to cut
                timer.refine_cut = {"units_per_batch": balance.total, "network_thread_units": balance.history}
        torch.set_num_threads(threads)
