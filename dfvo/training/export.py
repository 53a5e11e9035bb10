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
    """

    def __init__(self, dirpath: str | Path, weights_path: str | Path | None = None,
                 size: tuple[int | None, int | None] = (None, None), identity: str | None = None) -> None:
        # Lightning 2.6's save_last only rewrites last.ckpt when a top-k file was saved: "last" is its own top-1
        super().__init__(dirpath=dirpath, filename="last", monitor=None, save_top_k=1, enable_version_counter=False)
        self.weights_path = Path(weights_path) if weights_path is not None else None
        self.size, self.identity = size, identity

    def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
        super()._save_checkpoint(trainer, filepath)
        if self.weights_path is not None and trainer.is_global_zero:
            meta = weights_metadata({}, *self.size, global_step=trainer.global_step, epoch=trainer.current_epoch,
                                    source=filepath, identity=self.identity)
            export_weights(trainer.lightning_module, self.weights_path, meta)
