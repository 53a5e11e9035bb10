"""Resumable shuffling for training loaders: the order of an epoch depends only on (seed, epoch), DDP shards are
disjoint, and a run resumed from a checkpoint written mid-epoch skips the batches already trained.

The training position (epoch, batches of that epoch already trained) is saved in every checkpoint by the *stateful*
loader (:class:`ResumableLoader`, Lightning's ``state_dict`` / ``load_state_dict`` protocol of dataloaders).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator

import torch
from torch.utils.data import DataLoader, Sampler

__all__ = ["ResumableSampler", "ResumableLoader", "step_generator"]

log = logging.getLogger("dfvo.training")


def step_generator(seed: int, step: int, rank: int = 0, stream: int = 0) -> torch.Generator:
    """A CPU generator for the random draws of one training step: seeded by (``seed``, ``step``, DDP ``rank``,
    ``stream``) only, so a resumed run draws what an uninterrupted one drew, ranks draw differently, and separate
    consumers of one step (``stream`` 0: the data's sampling, 1: the module's augmentation) draw independently."""
    g = torch.Generator()
    g.manual_seed(((int(seed) * 1_000_003 + int(step)) * 1009 + int(rank)) * 31 + int(stream))
    return g


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
        shuffle: False: every epoch is ``0, 1, ..., num_samples - 1`` (datasets whose item i is the batch of step i).
    """

    def __init__(self, num_samples: int, batch_size: int, seed: int = 0, num_replicas: int = 1, rank: int = 0,
                 drop_last: bool = False, epoch_fn: Callable[[], int] | None = None,
                 position_fn: Callable[[], tuple[int, int]] | None = None, shuffle: bool = True) -> None:
        if num_samples <= 0 or batch_size <= 0:
            raise ValueError(f"ResumableSampler: need num_samples > 0 and batch_size > 0, got {num_samples}, "
                             f"{batch_size}")
        if not 0 <= rank < num_replicas:
            raise ValueError(f"ResumableSampler: rank {rank} outside [0, {num_replicas})")
        self.num_samples, self.batch_size, self.seed = num_samples, batch_size, seed
        self.num_replicas, self.rank, self.drop_last = num_replicas, rank, drop_last
        self.epoch_fn, self.position_fn, self.shuffle = epoch_fn, position_fn, shuffle
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
        if self.shuffle:
            g = torch.Generator()
            g.manual_seed(self.seed + epoch)
            order = torch.randperm(self.num_samples, generator=g).tolist()
        else:
            order = list(range(self.num_samples))
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
