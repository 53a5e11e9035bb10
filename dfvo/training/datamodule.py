"""LightningDataModule serving ``data=kitti_raw|kitti_odom|synthetic|kitti_raw_synthetic`` and the flow datasets
(``data=flyingchairs|flyingthings|sintel|kitti_flow``) for every task.

Config (``cfg.data``, see ``conf/data/*.yaml``): name, root, height, width, batch_size, num_workers, seed,
and per dataset: ``drives`` (kitti_raw), ``sequences`` (kitti_odom), ``seeds``/``num_frames`` (synthetic),
``resize``/``crop``/``train_split``/``val_split`` and the dataset's own keys (flyingchairs, flyingthings, sintel,
kitti_flow: frame pairs with true flow, :mod:`dfvo.data.flow_datasets`; ``val_split`` null = synthetic validation),
``val_seeds``/``val_num_frames``/``val_every`` (the synthetic validation worlds, always synthetic because
only they have true depth and flow). Samples are whatever the datasets return (keys of :mod:`dfvo.data`).

Shuffling uses :class:`ResumableSampler` (rank and world size from the trainer): the order of epoch e is a
permutation seeded by (seed, e) only, split into disjoint DDP shards. The training position (epoch, batches of
that epoch already trained) is saved in every checkpoint, by the *stateful* loader (:class:`ResumableLoader`) and
by the datamodule (:meth:`DFVODataModule.state_dict`), and on resume the sampler skips the batches already
consumed, so a run resumed from a checkpoint written mid-epoch (or at an epoch end) trains on the same batches, in
the same order, as an uninterrupted one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import ConcatDataset, DataLoader, Dataset, DistributedSampler, Sampler, Subset, default_collate

log = logging.getLogger("dfvo.training")

FLOW_DATASETS = ("flyingchairs", "flyingthings", "sintel", "kitti_flow")  # dfvo.data.flow_datasets: flow pairs only
DATASETS = ("kitti_raw", "kitti_odom", "synthetic", "kitti_raw_synthetic", *FLOW_DATASETS)


def _get(cfg: Any, key: str, default: Any) -> Any:
    value = OmegaConf.select(cfg, key, default=default)
    return default if value is None else value


def collate_common_keys(samples: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack the keys present in every sample (a mixed KITTI + synthetic batch keeps the shared keys)."""
    keys = set(samples[0])
    for s in samples[1:]:
        keys &= set(s)
    return default_collate([{k: s[k] for k in keys} for s in samples])


class ResumableSampler(Sampler[int]):
    """Shuffling sampler whose order depends only on (seed, epoch) and that can start an epoch part-way.

    Epoch ``e`` is ``torch.randperm(num_samples)`` drawn from a generator seeded with ``seed + e`` (the order
    ``DistributedSampler(shuffle=True)`` gives), cut or padded to a multiple of ``num_replicas`` like
    ``DistributedSampler`` (``drop_last``) and sharded as ``indices[rank::num_replicas]``.

    The epoch is ``epoch_fn()`` when given (the trainer's ``current_epoch``: Lightning's ``set_epoch`` value is one
    too high after resuming from a checkpoint written at an epoch end), else the value of :meth:`set_epoch`.
    :meth:`load_state_dict` makes the next iteration the saved epoch without its first ``batches`` batches;
    ``len()`` stays the full shard, because Lightning counts the skipped batches as already done.

    Args:
        num_samples: size of the dataset.
        batch_size: samples per batch (to skip whole batches).
        seed: shuffling seed.
        num_replicas, rank: DDP world size and this process's rank.
        drop_last: drop the tail that does not divide evenly between replicas (else pad by repeating).
        epoch_fn: callable returning the current epoch (None: use :meth:`set_epoch`).
        position_fn: callable returning ``(epoch, batches already trained in it)`` for :meth:`state_dict`
            (None: the start of the current epoch).
    """

    def __init__(self, num_samples: int, batch_size: int, seed: int = 0, num_replicas: int = 1, rank: int = 0,
                 drop_last: bool = False, epoch_fn: Callable[[], int] | None = None,
                 position_fn: Callable[[], tuple[int, int]] | None = None) -> None:
        if num_samples <= 0 or batch_size <= 0:
            raise ValueError(f"ResumableSampler: need num_samples > 0 and batch_size > 0, got {num_samples}, "
                             f"{batch_size}")
        if not 0 <= rank < num_replicas:
            raise ValueError(f"ResumableSampler: rank {rank} outside [0, {num_replicas})")
        self.num_samples, self.batch_size, self.seed = num_samples, batch_size, seed
        self.num_replicas, self.rank, self.drop_last = num_replicas, rank, drop_last
        self.epoch_fn, self.position_fn = epoch_fn, position_fn
        self._epoch = 0
        self._resume: tuple[int, int] | None = None
        if drop_last and num_samples % num_replicas:
            self.shard_size = num_samples // num_replicas
        else:
            self.shard_size = math.ceil(num_samples / num_replicas)

    def set_epoch(self, epoch: int) -> None:
        """Epoch to shuffle for when no ``epoch_fn`` is given (Lightning calls this before every epoch)."""
        self._epoch = int(epoch)

    @property
    def epoch(self) -> int:
        """The epoch the next iteration shuffles for (the resumed one while a resume is pending)."""
        if self._resume is not None:
            return self._resume[0]
        return int(self.epoch_fn()) if self.epoch_fn is not None else self._epoch

    def indices(self, epoch: int) -> list[int]:
        """This rank's sample order for ``epoch`` (the whole epoch)."""
        g = torch.Generator()
        g.manual_seed(self.seed + epoch)
        order = torch.randperm(self.num_samples, generator=g).tolist()
        total = self.shard_size * self.num_replicas
        if total > len(order):  # pad by repeating, as DistributedSampler
            order += (order * math.ceil(total / len(order)))[:total - len(order)]
        return order[:total][self.rank::self.num_replicas]

    def __iter__(self) -> Iterator[int]:
        # a generator: the epoch is read when the first index is requested, i.e. when the epoch really starts
        epoch, skip = self.epoch, 0
        if self._resume is not None:
            epoch, skip = self._resume
            self._resume = None
        yield from self.indices(epoch)[skip * self.batch_size:]

    def __len__(self) -> int:
        return self.shard_size

    def state_dict(self) -> dict[str, int]:
        """Position to resume from: ``epoch`` and ``batches`` of it already trained, plus the settings that must
        match for the position to mean the same samples."""
        epoch, batches = self.position_fn() if self.position_fn is not None else (self.epoch, 0)
        return {"epoch": int(epoch), "batches": int(batches), "num_samples": self.num_samples,
                "batch_size": self.batch_size, "num_replicas": self.num_replicas, "seed": self.seed}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Make the next iteration start at ``state``'s position (skipping its ``batches`` batches). When the
        dataset size, batch size, world size or seed changed, the saved position means other samples: the
        epoch then starts from its beginning (logged)."""
        settings = ("num_samples", "batch_size", "num_replicas", "seed")
        now = {k: getattr(self, k) for k in settings}
        saved = {k: state.get(k) for k in settings}
        epoch, batches = int(state["epoch"]), int(state["batches"])
        if saved != now:
            log.warning("resume: the checkpoint's data position (epoch %d, batch %d) was saved with %s, this run has "
                        "%s; epoch %d starts from its first batch (not an exact resume)", epoch, batches, saved, now,
                        epoch)
            batches = 0
        self._resume = (epoch, batches)


class ResumableLoader(DataLoader):
    """Training ``DataLoader`` over a :class:`ResumableSampler` that Lightning saves in checkpoints and restores on
    resume (the ``state_dict`` / ``load_state_dict`` protocol of Lightning's stateful dataloaders)."""

    def state_dict(self) -> dict[str, int]:
        """The sampler's position (see :meth:`ResumableSampler.state_dict`)."""
        return self.sampler.state_dict()

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Restore the sampler's position (see :meth:`ResumableSampler.load_state_dict`)."""
        self.sampler.load_state_dict(state)


class OdometrySnippets(Dataset):
    """Temporal snippets (``image_prev``, ``image``, ``image_next`` + the frame's other keys) of a frame dataset."""

    def __init__(self, frames: Dataset) -> None:
        if len(frames) < 3:
            raise ValueError(f"OdometrySnippets: need at least 3 frames, got {len(frames)}")
        self.frames = frames

    def __len__(self) -> int:
        return len(self.frames) - 2

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        sample = dict(self.frames[i + 1])
        sample.pop("timestamp", None)
        sample["image_prev"] = self.frames[i]["image"]
        sample["image_next"] = self.frames[i + 2]["image"]
        return sample


class DFVODataModule(L.LightningDataModule):
    """Training / validation data for :mod:`dfvo.training.runner` (task from ``cfg.model.task``)."""

    def __init__(self, cfg: DictConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.name = str(_get(cfg, "data.name", "synthetic"))
        if self.name not in DATASETS:
            raise ValueError(f"data.name: expected one of {DATASETS}, got {self.name!r}")
        self.task = str(_get(cfg, "model.task", "depth"))
        supervised_flow = self.task == "flow" and str(_get(cfg, "model.mode", "supervised")) == "supervised"
        if self.name in FLOW_DATASETS and self.task != "flow":
            raise ValueError(f"data={self.name} holds optical-flow frame pairs only; train it with "
                             f"model=flow_supervised or model=flow_self (model.task=flow), not model.task={self.task}")
        if supervised_flow and self.name not in ("synthetic", *FLOW_DATASETS):
            model = _get(cfg, "model.name", "flow_supervised")
            why = (" (its KITTI samples have none, and a mixed batch keeps only the keys every sample has)"
                   if self.name == "kitti_raw_synthetic" else " has none")
            raise ValueError(f"model={model} (model.mode=supervised) trains on true optical flow, which only "
                             f"data=synthetic and the flow datasets {FLOW_DATASETS} provide; data={self.name}{why}. "
                             "Use data=synthetic (or data=flyingchairs ...), or model=flow_self "
                             f"for real video (e.g. model=flow_self data={self.name} "
                             "model.init_from=<a flow_supervised last.ckpt>)")
        self.height = int(_get(cfg, "data.height", 192))
        self.width = int(_get(cfg, "data.width", 640))
        self.batch_size = int(_get(cfg, "data.batch_size", 4))
        self.num_workers = int(_get(cfg, "data.num_workers", 0))
        self.seed = int(_get(cfg, "data.seed", 0))
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None
        self._train_sampler: ResumableSampler | None = None
        self._resume_position: dict[str, int] | None = None

    # ------------------------------------------------------------ datasets
    def _synthetic(self, seeds: list[int], num_frames: int) -> Dataset:
        from dfvo.data.synthetic import SyntheticFlowDataset, SyntheticSequenceDataset
        cls = SyntheticFlowDataset if self.task == "flow" else SyntheticSequenceDataset
        return cls(list(seeds), num_frames, self.height, self.width)

    def _kitti_raw(self) -> Dataset:
        from dfvo.data.kitti_raw import KittiRawSnippets
        root = _get(self.cfg, "data.root", None) or _get(self.cfg, "data.kitti_raw_root", None)
        drives = _get(self.cfg, "data.drives", None)
        try:
            return KittiRawSnippets(root, self.height, self.width, drives=list(drives) if drives else None,
                                    stereo=True, temporal=True)
        except (OSError, ValueError) as err:
            raise type(err)(f"data={self.name} (data.root={root}): {err}") from err

    def _kitti_odom(self) -> Dataset:
        from dfvo.data.kitti_odometry import KittiOdometry
        root = _get(self.cfg, "data.root", None)
        seqs = [str(s) for s in _get(self.cfg, "data.sequences", ["06"])]
        try:
            return ConcatDataset([OdometrySnippets(KittiOdometry(root, s, self.height, self.width)) for s in seqs])
        except (OSError, ValueError) as err:
            raise type(err)(f"data=kitti_odom (data.root={root}, sequences={seqs}): {err}") from err

    def _flow_pairs(self, split: str, train: bool) -> Dataset:
        from dfvo.data.flow_datasets import build_flow_dataset
        return build_flow_dataset(self.name, lambda key, default: _get(self.cfg, f"data.{key}", default), split, train)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            syn = lambda: self._synthetic(list(_get(self.cfg, "data.seeds", [0])),  # noqa: E731
                                          int(_get(self.cfg, "data.num_frames", 50)))
            if self.name in FLOW_DATASETS:
                train = self._flow_pairs(str(_get(self.cfg, "data.train_split", "train")), train=True)
            elif self.name == "synthetic":
                train = syn()
            elif self.name == "kitti_raw":
                train = self._kitti_raw()
            elif self.name == "kitti_odom":
                train = self._kitti_odom()
            else:
                train = ConcatDataset([self._kitti_raw(), syn()])
            limit = _get(self.cfg, "data.max_train_samples", None)
            if limit:
                train = Subset(train, range(min(int(limit), len(train))))
            self.train_set = train
        if self.val_set is None:
            val_seeds = list(_get(self.cfg, "data.val_seeds", [1000]))
            val_split = _get(self.cfg, "data.val_split", None) if self.name in FLOW_DATASETS else None
            if val_split:  # the flow dataset's own validation pairs (centre crop)
                self.val_set = self._flow_pairs(str(val_split), train=False)
            elif val_seeds:
                val = self._synthetic(val_seeds, int(_get(self.cfg, "data.val_num_frames", 12)))
                every = int(_get(self.cfg, "data.val_every", 1))
                self.val_set = Subset(val, range(0, len(val), max(every, 1)))

    # ------------------------------------------------------------ loaders
    def _rank(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 1, 0
        return int(trainer.world_size), int(trainer.global_rank)

    # ------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The training data position, saved by Lightning in every checkpoint (beside the loader's own copy).

        Lightning hands a stateful loader its saved state only when the loader is built after the checkpoint was
        restored; a module that reads ``trainer.estimated_stepping_batches`` in ``configure_optimizers`` (as
        :class:`~dfvo.training.depth_module.DepthPoseModule` does) builds it before. The datamodule's state is
        restored before either, so :meth:`train_dataloader` can always start at the saved position."""
        return {"train_position": self._train_sampler.state_dict()} if self._train_sampler is not None else {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Keep the saved training data position for the next :meth:`train_dataloader`."""
        self._resume_position = state_dict.get("train_position")

    def _epoch(self) -> int:
        return int(self.trainer.current_epoch)

    def _position(self) -> tuple[int, int]:
        """(epoch, batches of it already trained) of the attached trainer: the next batch to train. A finished
        epoch (all its batches trained; a checkpoint written at its end) is the start of the next one."""
        trainer = self.trainer
        done = int(trainer.fit_loop.epoch_loop.batch_progress.current.ready)
        if done >= trainer.num_training_batches:
            return int(trainer.current_epoch) + 1, 0
        return int(trainer.current_epoch), done

    def train_dataloader(self) -> DataLoader:
        world, rank = self._rank()
        attached = getattr(self, "trainer", None) is not None
        sampler = ResumableSampler(len(self.train_set), self.batch_size, seed=self.seed, num_replicas=world, rank=rank,
                                   drop_last=world > 1, epoch_fn=self._epoch if attached else None,
                                   position_fn=self._position if attached else None)
        if self._resume_position:
            sampler.load_state_dict(self._resume_position)
            self._resume_position = None
        self._train_sampler = sampler
        return ResumableLoader(self.train_set, batch_size=self.batch_size, sampler=sampler,
                               num_workers=self.num_workers, drop_last=len(self.train_set) // world >= self.batch_size,
                               collate_fn=collate_common_keys, persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader | list:
        if self.val_set is None:
            return []
        world, rank = self._rank()
        sampler = DistributedSampler(self.val_set, num_replicas=world, rank=rank, shuffle=False)
        return DataLoader(self.val_set, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers)
