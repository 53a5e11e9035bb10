"""Data module of step-scheduled flow training (``data=flow_mix`` with ``model=flow_mix``): the cached synthetic
training worlds, the KITTI raw pairs, one batch per training step, and the held-out evaluation sets.

Config: ``cfg.data`` (:class:`dfvo.training.config.FlowMixTrainDataConfig`) and ``cfg.model.phases``
(:class:`dfvo.training.config.FlowPhase`): the run is one epoch whose item ``i`` is the whole batch of global step
``i`` (``DataLoader(batch_size=None)``), drawn with replacement by :func:`dfvo.training.sampling.step_generator`
(data seed, step, DDP rank):

    ``{"step": () int64, "sup": {...}, "self": {...}}``
    ``sup`` (phases with ``synthetic``): ``image``, ``image_next`` (B,3,h,w) float32 in [0,1], ``flow_fwd`` (B,2,h,w)
        image -> image_next on image, ``flow_bwd`` (B,2,h,w) image_next -> image on image_next, ``flow_fwd_valid``,
        ``flow_bwd_valid`` (B,1,h,w) bool; B = ``data.batch_size``; at the network size (h, w).
    ``self`` (phases with ``kitti``): ``image``, ``image_next`` (Bk,3,h,w) of KITTI raw pairs (k, k+s);
        Bk = ``data.kitti_batch_size``.

The order of the items is 0, 1, 2, ... (a :class:`~dfvo.training.sampling.ResumableSampler` without shuffling), so a
run resumed mid-epoch from ``last.ckpt`` continues at the next step's batch and trains exactly what an
uninterrupted run trains. Validation: one item per scenario of ``data.val_scenarios``
(:func:`dfvo.training.flow_renders.heldout_set`: ``name``, ``image``, ``image_next``, ``flow``, ``valid`` at the
working size), rendered when first needed and cached.

Training worlds are rendered (or read from ``data.cache_dir``) in :meth:`FlowMixDataModule.prepare_data` (once per
node) and loaded in :meth:`FlowMixDataModule.setup`; KITTI raw frames are decoded at the working size as inference
decodes them (bilinear), then resized to the network size (antialiased).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from dfvo.sources.networks import resize_images
from dfvo.synthetic import check_training_seeds
from dfvo.synthetic.trajectory import HANDHELD_SCENARIOS
from dfvo.training.config import FlowMixTrainDataConfig, FlowMode, FlowPhase, data_config, data_root, model_config
from dfvo.training.flow_renders import WorldRender, cached_world, heldout_set
from dfvo.training.sampling import ResumableLoader, ResumableSampler, step_generator

__all__ = ["SyntheticPairs", "kitti_raw_drives", "KittiRawPairs", "FlowStepBatches", "HeldOutSets", "FlowMixDataModule",
           "phase_at"]

log = logging.getLogger("dfvo.training")


def phase_at(phases: list[FlowPhase], step: int) -> tuple[FlowPhase, int]:
    """The phase of global ``step`` and the step at which that phase starts (steps past the end: the last phase)."""
    start = 0
    for phase in phases:
        if step < start + phase.steps:
            return phase, start
        start += phase.steps
    return phases[-1], start - phases[-1].steps


class SyntheticPairs:
    """The pairs of rendered training worlds (:func:`dfvo.training.flow_renders.render_world` dicts), packed into
    tensors: frames (N,3,h,w) fp16, per pair the frame indices and the fp16 flows and validity of both directions.

    Args:
        worlds: the world renders. limit: keep only the first ``limit`` pairs (None: all).
    """

    def __init__(self, worlds: list[dict], limit: int | None = None) -> None:
        if not worlds:
            raise ValueError("SyntheticPairs: no training world")
        offset, firsts = 0, []
        for w in worlds:
            firsts.append(offset)
            offset += w["images"].shape[0]
        self.images = torch.cat([w["images"] for w in worlds])
        self.a = torch.cat([w["pairs"][:, 0] + first for w, first in zip(worlds, firsts)])
        self.b = torch.cat([w["pairs"][:, 1] + first for w, first in zip(worlds, firsts)])
        self.flows = torch.cat([torch.stack([w["flow_fwd"], w["flow_bwd"]], 1) for w in worlds])
        self.valid = torch.cat([torch.stack([w["valid_fwd"], w["valid_bwd"]], 1) for w in worlds])
        if limit is not None:
            self.a, self.b, self.flows, self.valid = (x[:limit] for x in (self.a, self.b, self.flows, self.valid))

    def __len__(self) -> int:
        return len(self.a)

    def take(self, pick: torch.Tensor) -> dict[str, torch.Tensor]:
        """The pairs ``pick`` (B,) as a float32 batch (keys of the module docstring's ``sup``)."""
        flows, valid = self.flows[pick].float(), self.valid[pick]
        return {"image": self.images[self.a[pick]].float(), "image_next": self.images[self.b[pick]].float(),
                "flow_fwd": flows[:, 0], "flow_bwd": flows[:, 1], "flow_fwd_valid": valid[:, 0],
                "flow_bwd_valid": valid[:, 1]}


def kitti_raw_drives(root: str | Path, drives: list[str] | None, working: tuple[int, int],
                     held_out: Sequence[str] = ()) -> Any:
    """The KITTI raw drives under ``root`` (``drives``, or all but ``held_out``; file lists and calibration read, no
    image decoded): a :class:`dfvo.data.kitti_raw.KittiRawSnippets`. Raises the dataset's one-line errors for a
    root without the layout."""
    from dfvo.data.kitti_raw import KittiRawSnippets

    return KittiRawSnippets(root, working[0], working[1], drives=drives, stereo=False, temporal=True,
                            held_out=held_out)


class KittiRawPairs:
    """Frame pairs (k, k+s), s in ``frame_skips``, within every KITTI raw drive under ``root``, decoded as inference
    decodes them (bilinear to the working size ``working``), then resized (antialiased) to ``size``; fp16 in memory.

    Raises:
        DatasetNotFoundError / DatasetError: a root without the KITTI raw layout (one line naming the folder).
    """

    def __init__(self, root: str | Path, drives: list[str] | None, size: tuple[int, int], working: tuple[int, int],
                 frame_skips: list[int], held_out: Sequence[str] = ()) -> None:
        snippets = kitti_raw_drives(root, drives, working, held_out)
        frames, pairs = [], []
        for drive in snippets.drives:
            first = len(frames)
            for path in drive.left:
                frames.append(resize_images(drive.load(path)[None], size)[0].half())
            n = len(drive.left)
            pairs += [(first + k, first + k + s) for s in frame_skips for k in range(n - s)]
        if not pairs:
            raise ValueError(f"KITTI raw under {root}: no pair (k, k+s) for frame_skips={frame_skips}")
        self.frames = torch.stack(frames)
        self.pairs = torch.tensor(pairs, dtype=torch.int64)
        self.num_drives = len(snippets.drives)

    def __len__(self) -> int:
        return len(self.pairs)

    def take(self, pick: torch.Tensor) -> dict[str, torch.Tensor]:
        """The pairs ``pick`` (B,) as a float32 batch (``image``, ``image_next``)."""
        p = self.pairs[pick]
        return {"image": self.frames[p[:, 0]].float(), "image_next": self.frames[p[:, 1]].float()}


class FlowStepBatches(Dataset):
    """Item ``i``: the batch of global training step ``i`` (see the module docstring), drawn with replacement by
    ``step_generator(seed, i, rank, stream=0)``: first the synthetic picks, then the KITTI picks."""

    def __init__(self, phases: list[FlowPhase], synthetic: SyntheticPairs | None, kitti: KittiRawPairs | None,
                 batch_size: int, kitti_batch_size: int, seed: int, rank: int = 0) -> None:
        self.phases, self.synthetic, self.kitti = phases, synthetic, kitti
        self.batch_size, self.kitti_batch_size, self.seed, self.rank = batch_size, kitti_batch_size, seed, rank
        self.total = sum(p.steps for p in phases)

    def __len__(self) -> int:
        return self.total

    def __getitem__(self, step: int) -> dict[str, Any]:
        phase, _ = phase_at(self.phases, step)
        g = step_generator(self.seed, step, self.rank, stream=0)
        out: dict[str, Any] = {"step": torch.tensor(step)}
        if phase.synthetic:
            assert self.synthetic is not None
            out["sup"] = self.synthetic.take(torch.randint(len(self.synthetic), (self.batch_size,), generator=g))
        if phase.kitti:
            assert self.kitti is not None
            out["self"] = self.kitti.take(torch.randint(len(self.kitti), (self.kitti_batch_size,), generator=g))
        return out


class HeldOutSets(Dataset):
    """Item ``i``: the held-out set of scenario ``scenarios[i]`` (:func:`dfvo.training.flow_renders.heldout_set`),
    rendered when first asked for and kept (on disk in ``cache_dir``, and in memory)."""

    def __init__(self, scenarios: list[str], seeds: list[int], frames: int, working: tuple[int, int], every: int,
                 cache_dir: str | None, device: str = "cpu") -> None:
        self.scenarios, self.seeds, self.frames, self.working = list(scenarios), list(seeds), frames, working
        self.every, self.cache_dir, self.device = every, cache_dir, device
        self._sets: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.scenarios)

    def __getitem__(self, i: int) -> dict[str, Any]:
        if i not in self._sets:
            self._sets[i] = heldout_set(self.scenarios[i], self.seeds, self.frames, self.working, self.every,
                                        self.cache_dir, self.device)
        s = self._sets[i]
        return {"name": s["name"], **{k: s[k] for k in ("image", "image_next", "flow", "valid")}}


class FlowMixDataModule(L.LightningDataModule):
    """Training and validation data of ``model=flow_mix data=flow_mix`` (see the module docstring).

    Args:
        cfg: the training config (``model`` with ``phases``, ``data`` of kind ``flow_mix``).

    Raises:
        ValueError: a model other than mode ``mixed``, a held-out seed among the training seeds, a phase with
            ``kitti`` and no KITTI raw root (one line naming the setting).
    """

    one_epoch_run = True  # the run is one epoch: item i is the batch of step i (the runner sets max_epochs=1)

    def __init__(self, cfg: DictConfig | dict) -> None:
        super().__init__()
        self.model = model_config(cfg)
        self.data: FlowMixTrainDataConfig = data_config(cfg)
        if not isinstance(self.data, FlowMixTrainDataConfig):
            raise ValueError(f"FlowMixDataModule: data={self.data.kind}; expected data=flow_mix")
        if self.model.task != "flow" or self.model.mode != FlowMode.mixed:
            raise ValueError(f"data=flow_mix gives step batches of the phases of model=flow_mix (model.mode=mixed); "
                             f"got model={self.model.name} (model.task={self.model.task})")
        check_training_seeds(self.data.seeds, "data.seeds")
        self.phases: list[FlowPhase] = list(self.model.phases)
        self.needs_synthetic = any(p.synthetic for p in self.phases)
        self.needs_kitti = any(p.kitti for p in self.phases)
        self.kitti_root = data_root(self.data) if self.needs_kitti else None  # one line when neither is set
        d = self.data
        self.size = (int(d.height), int(d.width))
        self.working = (self.size[0] * d.render_scale, self.size[1] * d.render_scale)
        if d.device != "cpu" and d.num_workers > 0:
            raise ValueError(f"data.device={d.device} renders in the main process; set data.num_workers=0")
        if self.needs_kitti:  # the layout is checked now, before minutes of rendering
            self._kitti_call(kitti_raw_drives, self.kitti_root, self._drives(), self.working,
                             self.data.held_out_drives)
        self.synthetic: SyntheticPairs | None = None
        self.kitti: KittiRawPairs | None = None
        self.val_set: HeldOutSets | None = None
        self._train_sampler: ResumableSampler | None = None
        self._resume_position: dict[str, int] | None = None

    @property
    def has_validation(self) -> bool:
        return bool(self.data.val_seeds) and bool(self.data.val_scenarios)

    @property
    def total_steps(self) -> int:
        """The run's steps (the phases' sum)."""
        return sum(p.steps for p in self.phases)

    # ------------------------------------------------------------ data
    def _drives(self) -> list[str] | None:
        return list(self.data.drives) if self.data.drives else None

    def _kitti_call(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` with the dataset's errors prefixed by the setting they came from."""
        try:
            return fn(*args)
        except (OSError, ValueError) as err:
            raise type(err)(f"data=flow_mix (data.root={self.kitti_root}): {err}") from err

    def _renders(self) -> list[WorldRender]:
        d = self.data
        speed = None if d.speed is None else (float(d.speed[0]) if len(d.speed) == 1 else
                                              (float(d.speed[0]), float(d.speed[1])))
        scenarios = [d.scenario[int(s) % len(d.scenario)] for s in d.seeds]
        return [WorldRender(seed=int(s), scenario=sc, speed=None if sc in HANDHELD_SCENARIOS else speed,
                            frames=d.num_frames, size=self.size, scale=d.render_scale,
                            skips=tuple(int(k) for k in d.frame_skips),
                            max_flow=None if d.max_flow is None else float(d.max_flow),
                            sensor_variation=d.sensor_variation) for s, sc in zip(d.seeds, scenarios)]

    def _worlds(self) -> Iterator[dict]:
        """The training worlds in seed order (rendered or read from the cache), stopping once
        ``data.max_train_samples`` pairs are there."""
        have, limit = 0, self.data.max_train_samples
        for render in self._renders():
            t0 = time.perf_counter()
            world = cached_world(render, self.data.cache_dir, self.data.device)
            log.info("training world %s: %d pairs (%.1f s)", render.tag, len(world["pairs"]), time.perf_counter() - t0)
            yield world
            have += len(world["pairs"])
            if limit is not None and have >= limit:
                return

    def prepare_data(self) -> None:
        """Render the missing training worlds into ``data.cache_dir`` (once per node; nothing without a cache)."""
        if self.needs_synthetic and self.data.cache_dir is not None:
            for _ in self._worlds():
                pass

    def setup(self, stage: str | None = None) -> None:
        if self.needs_synthetic and self.synthetic is None:
            self.synthetic = SyntheticPairs(list(self._worlds()), self.data.max_train_samples)
            log.info("synthetic training pairs: %d", len(self.synthetic))
        if self.needs_kitti and self.kitti is None:
            self.kitti = self._kitti_call(KittiRawPairs, self.kitti_root, self._drives(), self.size, self.working,
                                          list(self.data.frame_skips), self.data.held_out_drives)
            log.info("KITTI raw pairs: %d from %d drives", len(self.kitti), self.kitti.num_drives)
        if self.has_validation and self.val_set is None:
            d = self.data
            self.val_set = HeldOutSets(list(d.val_scenarios), list(d.val_seeds), d.val_num_frames, self.working,
                                       d.val_every, d.cache_dir, d.device)

    # ------------------------------------------------------------ checkpoints (see DFVODataModule)
    def state_dict(self) -> dict[str, Any]:
        """The training position (saved by Lightning in every checkpoint, beside the loader's own copy)."""
        return {"train_position": self._train_sampler.state_dict()} if self._train_sampler is not None else {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._resume_position = state_dict.get("train_position")

    def _position(self) -> tuple[int, int]:
        trainer = self.trainer
        done = int(trainer.fit_loop.epoch_loop.batch_progress.current.ready)
        if done >= trainer.num_training_batches:
            return int(trainer.current_epoch) + 1, 0
        return int(trainer.current_epoch), done

    # ------------------------------------------------------------ loaders
    def _rank(self) -> int:
        trainer = getattr(self, "trainer", None)
        return int(trainer.global_rank) if trainer is not None else 0

    def _pin_memory(self) -> bool:
        trainer = getattr(self, "trainer", None)
        return trainer is not None and type(trainer.accelerator).__name__ == "CUDAAccelerator"

    def train_dataloader(self) -> DataLoader:
        steps = FlowStepBatches(self.phases, self.synthetic, self.kitti, self.data.batch_size,
                                self.data.kitti_batch_size, self.data.seed, self._rank())
        attached = getattr(self, "trainer", None) is not None
        # every rank iterates the steps in order (its batches differ by the rank in the draw's seed)
        sampler = ResumableSampler(len(steps), 1, seed=self.data.seed, shuffle=False,
                                   epoch_fn=(lambda: int(self.trainer.current_epoch)) if attached else None,
                                   position_fn=self._position if attached else None)
        if self._resume_position:
            sampler.load_state_dict(self._resume_position)
            self._resume_position = None
        self._train_sampler = sampler
        return ResumableLoader(steps, batch_size=None, sampler=sampler, num_workers=self.data.num_workers,
                               persistent_workers=self.data.num_workers > 0, pin_memory=self._pin_memory())

    def val_dataloader(self) -> DataLoader | list:
        if self.val_set is None:
            return []
        trainer = getattr(self, "trainer", None)
        world, rank = (int(trainer.world_size), int(trainer.global_rank)) if trainer is not None else (1, 0)
        sampler = DistributedSampler(self.val_set, num_replicas=world, rank=rank, shuffle=False)
        return DataLoader(self.val_set, batch_size=None, sampler=sampler, num_workers=0)
