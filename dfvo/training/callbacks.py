"""Callbacks of a training run: NaN stop, model identity in checkpoints, logging step after a resume, validation at
a ``max_steps`` stop, the channels-last memory layout, and console lines of the metrics."""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY

__all__ = ["NaNGuard", "ModelIdentity", "LoggedStepAfterResume", "ValidateAtStop", "ChannelsLast", "ConsoleMetrics",
           "total_steps", "eta_text"]

log = logging.getLogger("dfvo.training")


class NaNGuard(Callback):
    """Stop training with a clear message when the training loss is not finite."""

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        loss = outputs["loss"] if isinstance(outputs, dict) else outputs
        if loss is not None and not torch.isfinite(torch.as_tensor(loss)).all():
            raise FloatingPointError(
                f"training loss is {float(loss)} at step {trainer.global_step} (epoch {trainer.current_epoch}, "
                f"batch {batch_idx}); stopped. Resume from the last checkpoint with a lower model.lr, or check "
                "the data (images in [0,1], valid intrinsics).")


class ModelIdentity(Callback):
    """Write the model identity into every checkpoint."""

    def __init__(self, identity: str) -> None:
        self.identity = identity

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict) -> None:
        checkpoint[MODEL_IDENTITY_KEY] = self.identity


class LoggedStepAfterResume(Callback):
    """Make a resumed run log its first (and so every later) point at ``global_step``, as an uninterrupted run.

    Lightning 2.6 restores its logging step (``fit_loop.epoch_loop._batches_that_stepped``) one too high when the
    checkpoint was written at the end of an epoch (for example when ``trainer.max_steps`` stopped the run on an
    epoch's last batch), so every point of the resumed run is logged one step late. Without gradient accumulation,
    and with one optimiser step per batch, the logging step of a batch is its ``global_step``; at the first batch
    after a resume this callback sets it back when the two differ.
    """

    def __init__(self) -> None:
        self._resumed = False

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._resumed = trainer.ckpt_path is not None

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if not self._resumed:
            return
        self._resumed = False
        epoch_loop = trainer.fit_loop.epoch_loop
        if (pl_module.automatic_optimization and trainer.accumulate_grad_batches == 1
                and getattr(epoch_loop, "_batches_that_stepped", None) not in (None, trainer.global_step)):
            epoch_loop._batches_that_stepped = trainer.global_step


class ValidateAtStop(Callback):
    """Validate the last step of a run that ``trainer.max_steps`` stops, also mid-epoch.

    Lightning validates at the end of an epoch; a run stopped by ``max_steps`` before that never validates, so the
    ``best`` checkpoint's monitored metric (e.g. ``val/abs_rel``) does not exist. At the batch that reaches
    ``max_steps`` this callback requests the stop itself (``trainer.should_stop``), and Lightning runs the validation
    loop before stopping (as for early stopping); the checkpoints written at the end then see the metric.
    """

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        if 0 < trainer.max_steps <= trainer.global_step:
            trainer.should_stop = True


def to_channels_last(batch: Any) -> None:
    """Make the 4-D floating tensors of a batch dict (images, flows, depths: (B,C,H,W)) channels-last, in place."""
    if isinstance(batch, dict):
        for key, value in batch.items():
            if isinstance(value, torch.Tensor) and value.dim() == 4 and value.is_floating_point():
                batch[key] = value.contiguous(memory_format=torch.channels_last)


class ChannelsLast(Callback):
    """NHWC (channels-last) memory layout for the module's 4-D weights (convolutions) and the batches' images, which
    lets cuDNN's NHWC kernels run under mixed precision (``trainer.channels_last``). The values are unchanged."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        pl_module.to(memory_format=torch.channels_last)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        to_channels_last(batch)

    def on_validation_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                                  batch_idx: int, dataloader_idx: int = 0) -> None:
        to_channels_last(batch)


def _scalars(metrics: dict[str, Any], prefix: str) -> str:
    items = []
    for key in sorted(metrics):
        if key.startswith(prefix):
            value = torch.as_tensor(metrics[key])
            if value.numel() == 1 and math.isfinite(float(value)):
                items.append(f"{key}={float(value):.4g}")
    return " ".join(items)


def total_steps(trainer: L.Trainer) -> int | None:
    """The step count the run ends at (``max_steps``, else epochs x batches per epoch; None: unknown)."""
    if trainer.max_steps > 0:
        return int(trainer.max_steps)
    try:
        total = trainer.estimated_stepping_batches
    except Exception:  # noqa: BLE001 - Lightning raises several kinds before the loaders exist
        return None
    return int(total) if math.isfinite(total) else None


def eta_text(seconds: float) -> str:
    """``1d 02:03`` / ``02:03`` (hours:minutes) / ``--`` for an unknown time."""
    if not math.isfinite(seconds) or seconds < 0:
        return "--"
    minutes = int(round(seconds / 60.0))
    days, minutes = divmod(minutes, 24 * 60)
    text = f"{minutes // 60:02d}:{minutes % 60:02d}"
    return f"{days}d {text}" if days else text


class ConsoleMetrics(Callback):
    """One log line every ``every`` training steps (step of the total, learning rate, steps per hour since the start
    or resume, the time left at that rate, the logged ``train/`` scalars) and one after each validation (the ``val/``
    scalars): a readable record of a run without a progress bar (``trainer.print_every_n_steps``), e.g. one in the
    background writing to a log file (``scripts/campaign.sh``)."""

    def __init__(self, every: int) -> None:
        self.every = int(every)
        self._start: tuple[float, int] | None = None

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start = (time.monotonic(), int(trainer.global_step))
        total = total_steps(trainer)
        log.info("training from step %d of %s", trainer.global_step, total if total is not None else "?")

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        step = int(trainer.global_step)
        if self.every <= 0 or step % self.every or self._start is None:
            return
        t0, step0 = self._start
        per_hour = (step - step0) / max(time.monotonic() - t0, 1e-9) * 3600.0
        total = total_steps(trainer)
        left = (total - step) / per_hour * 3600.0 if total is not None and per_hour > 0 else float("nan")
        lr = trainer.optimizers[0].param_groups[0]["lr"] if trainer.optimizers else float("nan")
        log.info("step %d/%s lr %.3g %.0f steps/h ETA %s %s", step, total if total is not None else "?", lr,
                 per_hour, eta_text(left), _scalars(trainer.callback_metrics, "train/"))

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.every > 0 and not trainer.sanity_checking:
            log.info("validation at step %d: %s", trainer.global_step, _scalars(trainer.callback_metrics, "val/"))
