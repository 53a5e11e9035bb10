"""LightningDataModule serving every ``data=KIND`` of ``dfvo/conf/train/data/`` for every task.

Config: ``cfg.data``, typed by its kind's schema (:data:`dfvo.training.config.TRAIN_DATA_SCHEMAS`): video kinds
(``synthetic``, ``kitti_raw``, ``kitti_odom``, ``kitti_raw_synthetic``) give temporal snippets (i-s, i, i+s) for every
gap s of ``data.frame_skips`` (depth-pose: the target and its source views; flow: the pairs i-s → i, i → i+s; the
synthetic flow set gives the pairs (k, k+s) with their true flow); the flow pair kinds (``flyingchairs``,
``flyingthings``, ``sintel``, ``kitti_flow``, :mod:`dfvo.data.flow_datasets`) give pairs with true flow. Validation is
on the synthetic worlds of ``data.val_seeds`` (true depth and flow; the default scenario at gap 1, so the metric stays
comparable across training settings) or a flow dataset's ``data.val_split``. Dataset roots come from ``data.root`` or
the kind's environment variable (:func:`dfvo.training.config.data_root`). Samples are whatever the datasets return
(keys of :mod:`dfvo.data`).

Shuffling uses :class:`~dfvo.training.sampling.ResumableSampler` (rank and world size from the trainer): the order of
epoch e is a permutation seeded by (seed, e) only, split into disjoint DDP shards. The training position is saved in
every checkpoint, by the stateful loader and by the datamodule (:meth:`DFVODataModule.state_dict`), so a run resumed
from a checkpoint written mid-epoch (or at an epoch end) trains on the same batches, in the same order, as an
uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import logging
from enum import Enum
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig
from torch.utils.data import ConcatDataset, DataLoader, Dataset, DistributedSampler, Subset, default_collate

from dfvo.data.flow_datasets import build_flow_dataset
from dfvo.data.kitti_odometry import KittiOdometry
from dfvo.data.kitti_raw import KittiRawSnippets
from dfvo.synthetic import SyntheticFlowDataset, SyntheticSequenceDataset, check_training_seeds
from dfvo.training.config import (
    FlowMode,
    FlowPairTrainDataConfig,
    KittiOdomTrainDataConfig,
    KittiRawSyntheticTrainDataConfig,
    KittiRawTrainDataConfig,
    TrainDataConfig,
    WorldsTrainDataConfig,
    data_config,
    data_root,
    model_config,
)
from dfvo.training.sampling import ResumableLoader, ResumableSampler
from dfvo.training.snippets import SkipSnippets

__all__ = ["DFVODataModule", "collate_common_keys", "ResumableSampler", "ResumableLoader"]

log = logging.getLogger("dfvo.training")


# keys a sample may lack, filled with the value that means "none here" for the others of its batch: true depth
# (synthetic worlds) is <= 0 where there is none (dfvo.losses.depth_supervision), and so are a camera height (KITTI
# samples; dfvo.losses.road_height) and a stereo matcher's depth hint (KITTI samples with data.depth_hints)
FILL_MISSING = {"depth": 0.0, "camera_height": 0.0, "depth_hint": 0.0}


def collate_common_keys(samples: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack the keys present in every sample (a mixed KITTI + synthetic batch keeps the shared keys), and those of
    :data:`FILL_MISSING` present in some, filled where missing."""
    keys = set(samples[0])
    for s in samples[1:]:
        keys &= set(s)
    fill = {k: v for k, v in FILL_MISSING.items() if k not in keys and any(k in s for s in samples)}
    for key, value in fill.items():
        like = next(s[key] for s in samples if key in s)
        samples = [s if key in s else {**s, key: torch.full_like(like, value)} for s in samples]
    return default_collate([{k: s[k] for k in keys | set(fill)} for s in samples])


class DFVODataModule(L.LightningDataModule):
    """Training / validation data for :mod:`dfvo.training.runner` (the task from ``cfg.model``).

    Args:
        cfg: the training config (``model`` and ``data`` nodes; see :mod:`dfvo.training.config`).

    Raises:
        ValueError: settings that do not fit together (supervised flow on data without true flow, a flow dataset
            for a depth model), or a bad value (one line naming the setting).
    """

    def __init__(self, cfg: DictConfig | dict) -> None:
        super().__init__()
        self.model = model_config(cfg)
        self.data: TrainDataConfig = data_config(cfg)
        self.name = self.data.kind
        self.task = self.model.task
        flow_pairs = isinstance(self.data, FlowPairTrainDataConfig)
        if flow_pairs and self.task != "flow":
            raise ValueError(f"data={self.name} holds optical-flow frame pairs only; train it with "
                             f"model=flow_supervised or model=flow_self (model.task=flow), not model.task={self.task}")
        supervised_flow = self.task == "flow" and self.model.mode == FlowMode.supervised
        if supervised_flow and not (flow_pairs or self.name == "synthetic"):
            why = (" (its KITTI samples have none, and a mixed batch keeps only the keys every sample has)"
                   if self.name == "kitti_raw_synthetic" else " has none")
            raise ValueError(f"model={self.model.name} (model.mode=supervised) trains on true optical flow, which "
                             f"only data=synthetic and the flow datasets (data=flyingchairs|flyingthings|sintel|"
                             f"kitti_flow) provide; data={self.name}{why}. Use data=synthetic (or data=flyingchairs "
                             f"...), or model=flow_self for real video (e.g. model=flow_self data={self.name} "
                             "model.init_from=<a flow_supervised weights.safetensors or last.ckpt>)")
        if isinstance(self.data, WorldsTrainDataConfig):
            check_training_seeds(self.data.seeds, "data.seeds")
            if self.data.device != "cpu" and self.data.num_workers > 0:
                raise ValueError(f"data.device={self.data.device} renders in the main process; set "
                                 "data.num_workers=0")
        self.batch_size = self.data.batch_size
        self.num_workers = self.data.num_workers
        self.seed = self.data.seed
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None
        self._train_sampler: ResumableSampler | None = None
        self._resume_position: dict[str, int] | None = None

    @property
    def has_validation(self) -> bool:
        """Whether the config gives validation data (a flow dataset's ``val_split`` or synthetic ``val_seeds``)."""
        return bool(getattr(self.data, "val_split", None)) or bool(self.data.val_seeds)

    @property
    def frame_skips(self) -> list[int]:
        """The gaps s of the training snippets / pairs (``[1]`` for the flow pair datasets)."""
        return list(getattr(self.data, "frame_skips", [1]))

    # ------------------------------------------------------------ datasets
    def _synthetic(self, seeds: list[int], num_frames: int, frame_skips: list[int], train: bool = True) -> Dataset:
        """Synthetic worlds: the training distribution (scenario, speed, turn rate of ``data``) when ``train``, else
        the default worlds (validation stays comparable across training settings)."""
        d = self.data
        cls = SyntheticFlowDataset if self.task == "flow" else SyntheticSequenceDataset
        world: dict[str, Any] = {"device": d.device} if isinstance(d, WorldsTrainDataConfig) else {}
        if train and isinstance(d, WorldsTrainDataConfig):
            world["scenario"] = list(d.scenario)
            for key in ("speed", "turn_rate"):
                value = getattr(d, key)
                if value is not None:
                    world[key] = value[0] if len(value) == 1 else tuple(value)
            if d.shadows:
                world["shadows"] = True
        if cls is SyntheticSequenceDataset:  # (validation worlds of the other datasets: small, kept)
            world["keep_frames"] = bool(getattr(d, "keep_frames", True))
        return cls(list(seeds), num_frames, d.height, d.width, frame_skips=frame_skips, **world)

    def _need_stereo(self) -> bool:
        return self.task == "depth" and bool(getattr(self.model, "stereo", False))

    def _kitti_raw(self, data: KittiRawTrainDataConfig | KittiRawSyntheticTrainDataConfig) -> Dataset:
        root = data_root(data)
        drives = list(data.drives) if data.drives else None
        stereo, skips, cache = self._need_stereo(), self.frame_skips, data.frame_cache_dir
        hints = data.depth_hints
        try:
            if skips == [1]:
                return self._with_height(KittiRawSnippets(root, data.height, data.width, drives=drives, stereo=stereo,
                                                          temporal=True, cache_dir=cache, held_out=data.held_out_drives,
                                                          hints=hints), data)
            # KittiRawSnippets has no gap: its frame-level form (temporal=False) needs stereo=True, so snippets with
            # gaps read the right images too (dropped below for models without stereo)
            frames = KittiRawSnippets(root, data.height, data.width, drives=drives, stereo=True, temporal=False,
                                      cache_dir=cache, held_out=data.held_out_drives,
                                      hints=hints)
        except (OSError, ValueError) as err:
            raise type(err)(f"data={self.name} (data.root={root}): {err}") from err
        sequences: dict[int, list[int]] = {}
        for index, (drive, _) in enumerate(frames.samples):
            sequences.setdefault(drive, []).append(index)
        snippets = SkipSnippets(frames, list(sequences.values()), skips)
        return self._with_height(snippets if stereo else _DropKeys(snippets, ("image_right", "T_right_left")), data)

    @staticmethod
    def _with_height(dataset: Dataset, data: KittiRawTrainDataConfig | KittiRawSyntheticTrainDataConfig) -> Dataset:
        """``dataset`` whose samples carry the rig's ``camera_height`` (() float32, metres) when the data gives one."""
        if data.camera_height is None:
            return dataset
        return _AddKeys(dataset, {"camera_height": torch.tensor(float(data.camera_height))})

    def _kitti_odom(self, data: KittiOdomTrainDataConfig) -> Dataset:
        root = data_root(data)
        seqs = [str(s) for s in data.sequences]
        try:
            parts, stereo = [], None if self._need_stereo() else False  # None: when the right images exist
            for seq in seqs:
                frames = KittiOdometry(root, seq, data.height, data.width, stereo=stereo)
                mono = KittiOdometry(root, seq, data.height, data.width, stereo=False) if frames.stereo else None
                parts.append(SkipSnippets(frames, [range(len(frames))], self.frame_skips, neighbours=mono))
            return ConcatDataset(parts)
        except (OSError, ValueError) as err:
            raise type(err)(f"data=kitti_odom (data.root={root}, sequences={seqs}): {err}") from err

    def _flow_pairs(self, split: str, train: bool) -> Dataset:
        data = dataclasses.replace(self.data, root=data_root(self.data))

        def get(key: str, default: Any) -> Any:
            value = getattr(data, key, None)
            value = value.value if isinstance(value, Enum) else value
            return default if value is None else value
        return build_flow_dataset(self.name, get, split, train)

    def setup(self, stage: str | None = None) -> None:
        d = self.data
        if self.train_set is None:
            if isinstance(d, FlowPairTrainDataConfig):
                train = self._flow_pairs(d.train_split, train=True)
            elif isinstance(d, KittiRawSyntheticTrainDataConfig):
                train = ConcatDataset([self._kitti_raw(d), self._synthetic(d.seeds, d.num_frames, self.frame_skips)])
            elif isinstance(d, WorldsTrainDataConfig):
                train = self._synthetic(d.seeds, d.num_frames, self.frame_skips)
            elif isinstance(d, KittiRawTrainDataConfig):
                train = self._kitti_raw(d)
            elif isinstance(d, KittiOdomTrainDataConfig):
                train = self._kitti_odom(d)
            else:
                raise ValueError(f"data={self.name}: no training set for {type(d).__name__}")
            if d.max_train_samples:
                train = Subset(train, range(min(d.max_train_samples, len(train))))
            self.train_set = train
        if self.val_set is None:
            val_split = getattr(d, "val_split", None)
            if val_split:  # the flow dataset's own validation pairs (centre crop)
                self.val_set = self._flow_pairs(val_split, train=False)
            elif d.val_seeds:
                val = self._synthetic(d.val_seeds, d.val_num_frames, [1], train=False)
                self.val_set = Subset(val, range(0, len(val), d.val_every))

    # ------------------------------------------------------------ loaders
    def _rank(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 1, 0
        return int(trainer.world_size), int(trainer.global_rank)

    def _pin_memory(self) -> bool:
        """Pinned host memory for a CUDA trainer (not for samples rendered on the GPU)."""
        trainer = getattr(self, "trainer", None)
        on_cuda = trainer is not None and type(trainer.accelerator).__name__ == "CUDAAccelerator"
        return on_cuda and getattr(self.data, "device", "cpu") == "cpu"

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
                               collate_fn=collate_common_keys, persistent_workers=self.num_workers > 0,
                               pin_memory=self._pin_memory())

    def val_dataloader(self) -> DataLoader | list:
        if self.val_set is None:
            return []
        world, rank = self._rank()
        sampler = DistributedSampler(self.val_set, num_replicas=world, rank=rank, shuffle=False)
        return DataLoader(self.val_set, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers,
                          pin_memory=self._pin_memory())


class _DropKeys(Dataset):
    """``dataset`` without some sample keys."""

    def __init__(self, dataset: Dataset, keys: tuple[str, ...]) -> None:
        self.dataset, self.keys = dataset, keys

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v for k, v in self.dataset[i].items() if k not in self.keys}


class _AddKeys(Dataset):
    """``dataset`` with constant sample keys added (the same tensor for every sample)."""

    def __init__(self, dataset: Dataset, keys: dict[str, torch.Tensor]) -> None:
        self.dataset, self.keys = dataset, keys

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {**self.dataset[i], **{k: v.clone() for k, v in self.keys.items()}}
