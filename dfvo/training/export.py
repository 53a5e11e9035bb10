"""The weights-only export of a training run: the network inference loads, as a small fp16 ``.safetensors`` file.

A run writes ``RUN/weights.safetensors`` beside its resumable ``RUN/checkpoints/last.ckpt`` whenever that is written
(:class:`LastCheckpoint`); ``scripts/export_checkpoint.py`` writes the same format from any checkpoint. Both use
:func:`weights_metadata`, so the file always says what it holds:

==================  =======================================================================================
key                 value (strings)
==================  =======================================================================================
``task``            ``flow`` or ``depth``
``variant``         FlowNet variant (flow)
``min_depth``       the DepthNet's depth range in metres (depth)
``max_depth``
``height``          the input size the network was trained at (inference resizes to it)
``width``
``global_step``     the training step of the weights; ``epoch`` its epoch
``source``          the checkpoint the weights are (or were written beside)
``dfvo_model``      the run's model identity ``task:name`` (when known)
==================  =======================================================================================

Load it with ``infer.py flow.checkpoint=RUN/weights.safetensors`` (or ``depth.checkpoint=``), or as
``model.init_from`` of another training run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY, save_weights

__all__ = ["WEIGHTS_NAME", "weights_metadata", "export_weights", "LastCheckpoint"]

WEIGHTS_NAME = "weights.safetensors"


def weights_metadata(network_meta: dict[str, str], height: int | None, width: int | None,
                     global_step: int | None = None, epoch: int | None = None, source: str | Path | None = None,
                     identity: str | None = None) -> dict[str, str]:
    """The metadata of an exported network (the table in the module docstring); None values are left out."""
    meta = dict(network_meta)
    extra: dict[str, Any] = {"height": height, "width": width, "global_step": global_step, "epoch": epoch,
                             "source": source, MODEL_IDENTITY_KEY: identity}
    meta.update({k: str(v) for k, v in extra.items() if v is not None})
    return meta


def export_weights(module: L.LightningModule, path: str | Path, metadata: dict[str, str],
                   dtype: torch.dtype = torch.float16) -> Path:
    """Write ``module.export_network()``'s network to ``path`` (``.safetensors``, floats as ``dtype``, atomic) with
    the network's own metadata and ``metadata`` (see :func:`weights_metadata`)."""
    net, meta = module.export_network()
    return save_weights(net, path, {**meta, **metadata}, dtype=dtype)


class LastCheckpoint(ModelCheckpoint):
    """``checkpoints/last.ckpt``, rewritten at every save point (no monitor), and, when ``weights_path`` is given,
    the weights-only export refreshed each time it is written (on the global-zero process).

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
        super()._save_checkpoint(trainer, filepath)
        if self.weights_path is not None and trainer.is_global_zero:
            meta = weights_metadata({}, *self.size, global_step=trainer.global_step, epoch=trainer.current_epoch,
                                    source=filepath, identity=self.identity)
            export_weights(trainer.lightning_module, self.weights_path, meta)
