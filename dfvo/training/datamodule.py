"""LightningDataModule serving ``data=kitti_raw|kitti_odom|synthetic|kitti_raw_synthetic`` for every task.

Config (``cfg.data``, see ``conf/data/*.yaml``): name, root, height, width, batch_size, num_workers, seed,
and per dataset: ``drives`` (kitti_raw), ``sequences`` (kitti_odom), ``seeds``/``num_frames`` (synthetic),
``val_seeds``/``val_num_frames``/``val_every`` (the synthetic validation worlds, always synthetic because
only they have true depth and flow). Samples are whatever the datasets return (keys of :mod:`dfvo.data`).

Shuffling uses a seeded ``DistributedSampler`` (rank and world size from the trainer): the order of epoch e is
a function of (seed, e) only, so a run resumed from a checkpoint sees the same batches as an uninterrupted one,
and DDP ranks see disjoint shards.
"""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import ConcatDataset, DataLoader, Dataset, DistributedSampler, Subset, default_collate

DATASETS = ("kitti_raw", "kitti_odom", "synthetic", "kitti_raw_synthetic")


def _get(cfg: Any, key: str, default: Any) -> Any:
    value = OmegaConf.select(cfg, key, default=default)
    return default if value is None else value


def collate_common_keys(samples: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack the keys present in every sample (a mixed KITTI + synthetic batch keeps the shared keys)."""
    keys = set(samples[0])
    for s in samples[1:]:
        keys &= set(s)
    return default_collate([{k: s[k] for k in keys} for s in samples])


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
        self.height = int(_get(cfg, "data.height", 192))
        self.width = int(_get(cfg, "data.width", 640))
        self.batch_size = int(_get(cfg, "data.batch_size", 4))
        self.num_workers = int(_get(cfg, "data.num_workers", 0))
        self.seed = int(_get(cfg, "data.seed", 0))
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None

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

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            syn = lambda: self._synthetic(list(_get(self.cfg, "data.seeds", [0])),  # noqa: E731
                                          int(_get(self.cfg, "data.num_frames", 50)))
            if self.name == "synthetic":
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
            if val_seeds:
                val = self._synthetic(val_seeds, int(_get(self.cfg, "data.val_num_frames", 12)))
                every = int(_get(self.cfg, "data.val_every", 1))
                self.val_set = Subset(val, range(0, len(val), max(every, 1)))

    # ------------------------------------------------------------ loaders
    def _rank(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 1, 0
        return int(trainer.world_size), int(trainer.global_rank)

    def train_dataloader(self) -> DataLoader:
        world, rank = self._rank()
        sampler = DistributedSampler(self.train_set, num_replicas=world, rank=rank, shuffle=True, seed=self.seed,
                                     drop_last=world > 1)
        return DataLoader(self.train_set, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers,
                          drop_last=len(self.train_set) // world >= self.batch_size, collate_fn=collate_common_keys,
                          persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader | list:
        if self.val_set is None:
            return []
        world, rank = self._rank()
        sampler = DistributedSampler(self.val_set, num_replicas=world, rank=rank, shuffle=False)
        return DataLoader(self.val_set, batch_size=self.batch_size, sampler=sampler, num_workers=self.num_workers)
