"""The weights-only export of a training run: the network inference loads, as a small fp16 ``.safetensors`` file.

A run writes ``RUN/weights.safetensors`` beside its resumable ``RUN/checkpoints/last.ckpt`` whenever that is written
(:class:`LastCheckpoint`); ``scripts/export_checkpoint.py`` writes the same format from any checkpoint. Both use
:func:`weights_metadata`, so the file always says what it holds:

====================  =======================================================================================
key                   value (strings)
====================  =======================================================================================
``task``              ``flow`` or ``depth``
``variant``           FlowNet variant (flow)
``min_depth``         the DepthNet's depth range in metres (depth)
``max_depth``
``width_multiplier``  the DepthNet's channel multiplier (depth; ``model.width_multiplier``)
``height``            the input size the network was trained at (inference resizes to it)
``width``
``global_step``       the training step of the weights; ``epoch`` its epoch (of the whole run: ``continue_from``)
``source``            the checkpoint the weights are (or were written beside)
``dfvo_model``        the run's model identity ``task:name`` (when known)
====================  =======================================================================================

Load it with ``infer.py flow.checkpoint=RUN/weights.safetensors`` (or ``depth.checkpoint=``), or as
``model.init_from`` of another training run.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY, save_weights

__all__ = ["WEIGHTS_NAME", "PREVIOUS_NAME", "weights_metadata", "run_position", "export_weights", "durable_replace",
           "LastCheckpoint", "KeepWeights"]

WEIGHTS_NAME = "weights.safetensors"
PREVIOUS_NAME = "previous.ckpt"


def weights_metadata(network_meta: dict[str, str], height: int | None, width: int | None,
                     global_step: int | None = None, epoch: int | None = None, source: str | Path | None = None,
                     identity: str | None = None) -> dict[str, str]:
    """The metadata of an exported network (the table in the module docstring); None values are left out."""
    meta = dict(network_meta)
    extra: dict[str, Any] = {"height": height, "width": width, "global_step": global_step, "epoch": epoch,
                             "source": source, MODEL_IDENTITY_KEY: identity}
    meta.update({k: str(v) for k, v in extra.items() if v is not None})
    return meta


def run_position(trainer: L.Trainer) -> tuple[int, int]:
    """The step and epoch of the whole run: the trainer's, plus the module's ``steps_before`` / ``epochs_before``
    when the run continues another from its weights (``continue_from``, :mod:`dfvo.training.continuation`)."""
    module = trainer.lightning_module
    return (int(trainer.global_step) + int(getattr(module, "steps_before", 0)),
            int(trainer.current_epoch) + int(getattr(module, "epochs_before", 0)))


def export_weights(module: L.LightningModule, path: str | Path, metadata: dict[str, str],
                   dtype: torch.dtype = torch.float16) -> Path:
    """Write ``module.export_network()``'s network to ``path`` (``.safetensors``, floats as ``dtype``, atomic) with
    the network's own metadata and ``metadata`` (see :func:`weights_metadata`); with ``trainer.ema_decay`` the
    moving average of its weights (:mod:`dfvo.training.weight_average`, metadata ``weights: ema DECAY``)."""
    from dfvo.training.weight_average import averaged_network

    net, meta = module.export_network()
    average = averaged_network(module)
    if average is not None:
        net, meta = average, {**meta, "weights": f"ema {module.weight_average.decay:g}"}
    return save_weights(net, path, {**meta, **metadata}, dtype=dtype)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def durable_replace(tmp: Path, path: Path, keep_previous: Path | None = None) -> None:
    """Move the fully written ``tmp`` onto ``path`` so that a SIGKILL or a power loss at any moment leaves a whole
    file at ``path`` (the old one or the new one): ``tmp`` is flushed to disk first, the rename is atomic, and the
    folder entry is flushed after it. ``keep_previous``: the old ``path`` is kept there (a hard link made before the
    rename, itself swapped in atomically), one more whole file to fall back on."""
    _fsync(tmp)
    if keep_previous is not None and path.is_file():
        link = keep_previous.with_name(keep_previous.name + ".tmp")
        link.unlink(missing_ok=True)
        try:
            os.link(path, link)
        except OSError:  # a file system without hard links: no previous copy
            pass
        else:
            os.replace(link, keep_previous)
    os.replace(tmp, path)
    try:
        _fsync(path.parent)
    except OSError:  # some file systems cannot fsync a folder; the rename itself is done
        pass


class LastCheckpoint(ModelCheckpoint):
    """``checkpoints/last.ckpt``, rewritten at every save point (no monitor), and, when ``weights_path`` is given,
    the weights-only export refreshed each time it is written (on the global-zero process).

    Every write goes to ``last.ckpt.tmp`` and replaces ``last.ckpt`` only when whole and on disk
    (:func:`durable_replace`); the checkpoint it replaces stays as ``previous.ckpt``. A run killed at any moment
    (SIGKILL, power) so keeps a resumable checkpoint of at most ``every_n_steps`` steps ago (``resume=auto``,
    :mod:`dfvo.training.resume`).

    Args:
        dirpath: the checkpoint folder.
        weights_path: where the export goes (None: no export).
        size: (height, width) the network is trained at (metadata). identity: the model identity (metadata).
        every_n_steps: rewrite it every this many training steps, and at the end of the run (None: at every epoch end
            and validation, Lightning's default points).
    """

    def __init__(self, dirpath: str | Path, weights_path: str | Path | None = None,
                 size: tuple[int | None, int | None] = (None, None), identity: str | None = None,
                 every_n_steps: int | None = None) -> None:
        # Lightning 2.6's save_last only rewrites last.ckpt when a top-k file was saved: "last" is its own top-1
        super().__init__(dirpath=dirpath, filename="last", monitor=None, save_top_k=1, enable_version_counter=False,
                         every_n_train_steps=every_n_steps)
        self.weights_path = Path(weights_path) if weights_path is not None else None
        self.size, self.identity = size, identity

    @property
    def path(self) -> Path:
        """``DIR/last.ckpt``."""
        return Path(self.format_checkpoint_name({}))

    def save_now(self, trainer: L.Trainer) -> Path:
        """Write ``last.ckpt`` (and the export) for the trainer's current state, unless it was written at this step."""
        if self._last_global_step_saved != trainer.global_step or not self.path.is_file():
            self._save_checkpoint(trainer, str(self.path))
            self.best_model_path = self.last_model_path = str(self.path)  # what run_training reports
        return self.path

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        """Every ``every_n_steps`` steps (Lightning's own trigger), and with ``every_n_steps`` also at the step that
        ends the run or an epoch (a ``max_steps`` stop, the last batch): saved here, at the end of the step, the
        checkpoint resumes exactly like the periodic ones."""
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        if self._every_n_train_steps > 0 and not self._should_skip_saving_checkpoint(trainer):
            ends = (trainer.should_stop or 0 < trainer.max_steps <= trainer.global_step
                    or trainer.fit_loop.epoch_loop.batch_progress.is_last_batch)
            if ends:
                self.save_now(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """With ``every_n_steps``, a run whose last step was not saved yet (a stop requested after it) is saved."""
        super().on_train_end(trainer, pl_module)
        if self._every_n_train_steps > 0 and trainer.global_step > self._last_global_step_saved:
            self.save_now(trainer)

    def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
        path = Path(filepath)
        tmp = path.with_name(path.name + ".tmp")
        super()._save_checkpoint(trainer, str(tmp))  # Lightning's save (every rank takes part; global zero writes)
        if trainer.is_global_zero:
            durable_replace(tmp, path, keep_previous=path.with_name(PREVIOUS_NAME))
        trainer.strategy.barrier("dfvo_last_checkpoint")
        self._last_checkpoint_saved = filepath
        if self.weights_path is not None and trainer.is_global_zero:
            step, epoch = run_position(trainer)
            meta = weights_metadata({}, *self.size, global_step=step, epoch=epoch, source=filepath,
                                    identity=self.identity)
            export_weights(trainer.lightning_module, self.weights_path, meta)


class KeepWeights(L.Callback):
    """``RUN/weights_step{N}.safetensors`` (the fp16 export, as ``weights.safetensors``) at every ``every``-th
    training step: a long run's intermediate networks, kept for choosing among them afterwards
    (``trainer.keep_weights_every_n_steps``).

    Args:
        run_dir: the run folder. every: steps between two kept files. size, identity: the export's metadata.
    """

    def __init__(self, run_dir: str | Path, every: int, size: tuple[int | None, int | None] = (None, None),
                 identity: str | None = None) -> None:
        self.run_dir, self.every, self.size, self.identity = Path(run_dir), int(every), size, identity

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        step, epoch = run_position(trainer)
        if step % self.every or not trainer.is_global_zero:
            return
        meta = weights_metadata({}, *self.size, global_step=step, epoch=epoch, identity=self.identity)
        export_weights(pl_module, self.run_dir / f"weights_step{step}.safetensors", meta)
