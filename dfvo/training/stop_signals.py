"""Stopping a training run by SIGTERM (a cluster's time limit, ``kill``) or SIGINT (Ctrl-C) without losing it.

While :func:`stop_signals` is active (the whole of :func:`dfvo.training.runner.run_training`), both signals are
caught by :class:`StopOnSignal`:

- before training has started (data rendering or loading, building the model): the run stops at once with
  :class:`TrainingInterrupted` (nothing to save);
- during training: the step in progress finishes (or the validation batch in progress), then
  ``checkpoints/last.ckpt`` (and ``weights.safetensors``) are written for exactly that state and the run stops with
  :class:`TrainingInterrupted`; ``ckpt_path=RUN/checkpoints/last.ckpt`` resumes it exactly (the data position is in
  the checkpoint, as for the periodic ones);
- a second signal while the first is being handled stops at once.

``dfvo-train`` then prints one line and exits with 128 + the signal number: 143 (SIGTERM), 130 (SIGINT), as shells
and cluster schedulers expect of a process ended by a signal.
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback

from dfvo.training.export import LastCheckpoint

__all__ = ["TrainingInterrupted", "StopOnSignal", "stop_signals", "SIGNALS"]

log = logging.getLogger("dfvo.training")

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class TrainingInterrupted(Exception):
    """A training run stopped by a signal. ``exit_code`` is 128 + the signal number; ``checkpoint`` the ``last.ckpt``
    written for the state at the stop (None: stopped before training, or nothing could be written)."""

    def __init__(self, signum: int, step: int | None = None, checkpoint: Path | None = None) -> None:
        self.signum, self.step, self.checkpoint = int(signum), step, checkpoint
        name = signal.Signals(self.signum).name
        if checkpoint is not None:
            text = (f"stopped by {name} at step {step}; saved {checkpoint} (resume=auto continues the run from it, as "
                    f"ckpt_path={checkpoint} does)")
        elif step is None:
            text = f"stopped by {name} before training started; nothing to save"
        else:
            text = f"stopped by {name} at step {step}; no checkpoint written"
        super().__init__(text)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopOnSignal(Callback):
    """Finish the step (or validation batch) in progress when a stop signal arrives, write ``last.ckpt`` through
    ``last`` and stop the fit with :class:`TrainingInterrupted` (see the module docstring)."""

    def __init__(self, last: LastCheckpoint | None = None) -> None:
        self.last = last
        self.signum: int | None = None
        self.training = False
        self.trainer: L.Trainer | None = None
        self.saved: Path | None = None

    # ------------------------------------------------------------ the handler
    def handle(self, signum: int, frame: Any) -> None:
        """Signal handler: during training remember the signal (the step in progress finishes, then the hooks save
        and stop); before training, after it, or on a second signal, stop at once."""
        first = self.signum is None
        self.signum = signum
        if first and self.training:
            log.info("%s received: finishing the current step, then saving last.ckpt", signal.Signals(signum).name)
            return
        if self.trainer is None:
            raise TrainingInterrupted(signum)
        done = not self.training and self.last is not None and self.last.path.is_file()
        raise TrainingInterrupted(signum, int(self.trainer.global_step), self.last.path if done else None)

    # ------------------------------------------------------------ hooks
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.trainer, self.training = trainer, True
        if self.signum is not None:  # arrived while Lightning was setting up
            raise TrainingInterrupted(self.signum, int(trainer.global_step))

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.training = False

    def _check(self, trainer: L.Trainer) -> None:
        if self.signum is not None:
            raise TrainingInterrupted(self.signum, int(trainer.global_step))

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        self._check(trainer)

    def on_validation_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                                batch_idx: int, dataloader_idx: int = 0) -> None:
        if trainer.training or self.training:
            self._check(trainer)

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        """After a stop signal (whatever exception it caused: ours, Lightning's SIGTERMException, a DataLoader worker
        killed by the same signal), save the state of the last finished step."""
        if self.signum is None or not self.training or self.last is None or trainer.global_step == 0:
            return
        try:
            self.saved = self.last.save_now(trainer)
        except Exception as err:  # noqa: BLE001 - a failed save must not hide the stop
            log.error("could not write %s after %s: %s", self.last.path, signal.Signals(self.signum).name, err)

    def interrupted(self, step: int | None) -> TrainingInterrupted | None:
        """The :class:`TrainingInterrupted` describing the stop (None: no stop signal arrived)."""
        if self.signum is None:
            return None
        return TrainingInterrupted(self.signum, step if self.training or self.saved else None, self.saved)


@contextmanager
def stop_signals(stopper: StopOnSignal) -> Iterator[StopOnSignal]:
    """Route SIGINT and SIGTERM to ``stopper.handle`` (restoring the previous handlers after); in the main thread only
    (elsewhere Python cannot install handlers, and nothing is changed)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield stopper
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    for s in SIGNALS:
        signal.signal(s, stopper.handle)
    try:
        yield stopper
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
