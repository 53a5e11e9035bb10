"""``continue_from=``: continue a depth run whose resumable checkpoints are lost, from a weights export of the run.

A long depth run keeps its exact resumable state in ``RUN/checkpoints/last.ckpt`` (~200 MB: weights, optimiser,
data position); what can be committed for a new machine is its fp16 export ``weights.safetensors`` (~7 MB), which
records the step and epoch it was written at (:func:`dfvo.training.export.weights_metadata`). ``continue_from=FILE``
turns such a file back into the rest of the run:

- the depth network starts from the file's weights (as ``model.init_from``; the pose network and the optimiser
  start anew: they are not in the export);
- the run trains the epochs still to go (``trainer.max_epochs`` less the file's ``epoch``; the epoch the export was
  written in is trained again whole);
- the learning rate drops at the same step of the whole run as it would have (the module's ``steps_before``), and
  every export of the continued run records its step and epoch within the whole run, so a continuation can itself be
  continued.

It is not exact (Adam's moments are rebuilt and the data order differs); a run with a checkpoint resumes exactly
(``resume=auto``), and with both, the checkpoint is resumed and ``continue_from`` keeps shaping its schedule the same
way. ``scripts/campaign.sh`` sets it for a run restored from committed weights alone (``campaign/NAME/``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, open_dict

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY, CheckpointError, find_checkpoint, read_state_dict

__all__ = ["Continuation", "read_continuation", "continued_config"]


@dataclass(frozen=True)
class Continuation:
    """Where a continued run picks up: the weights file, the steps and whole epochs of the run before it."""

    path: Path
    steps_before: int
    epochs_before: int


def read_continuation(cfg: DictConfig, identity: str) -> Continuation | None:
    """The ``continue_from`` of a training config, read and checked (None: not set).

    Args:
        cfg: the composed training config. identity: the run's model identity ``task:name``.

    Raises:
        CheckpointError: the file is missing or unreadable, lacks ``global_step``/``epoch``, or holds another model.
        ValueError: not a depth run, or the file's epoch is at or past ``trainer.max_epochs``.
    """
    setting = cfg.get("continue_from")
    if not setting:
        return None
    if str(cfg.model.task) != "depth":
        raise ValueError(f"continue_from={setting}: only depth runs continue from their weights (a {cfg.model.task} "
                         "run's last.ckpt is small enough to keep: resume=auto)")
    path = find_checkpoint(str(setting), "continue_from")
    _, meta = read_state_dict(path, "depth network DepthNet", "continue_from")
    found = meta.get(MODEL_IDENTITY_KEY)
    if found != identity:
        raise CheckpointError(f"continue_from={path}: holds a {found!r} run's weights, not a {identity!r} one; "
                              "expected a weights export of this run (RUN/weights.safetensors)")
    try:
        steps, epochs = int(meta["global_step"]), int(meta["epoch"])
    except (KeyError, ValueError):
        raise CheckpointError(f"continue_from={path}: no global_step/epoch in its metadata; expected a weights export "
                              "written by a training run (RUN/weights.safetensors)") from None
    max_epochs = int(cfg.trainer.max_epochs)
    if not 0 <= epochs < max_epochs or steps < 0:
        raise ValueError(f"continue_from={path}: written at step {steps}, epoch {epochs}; expected an epoch below "
                         f"trainer.max_epochs={max_epochs} (the run would have nothing left to train)")
    return Continuation(path, steps, epochs)


def continued_config(cfg: DictConfig, cont: Continuation) -> DictConfig:
    """``cfg`` for the rest of the run: ``model.init_from`` the file, ``trainer.max_epochs`` the epochs to go."""
    out = copy.deepcopy(cfg)
    with open_dict(out):
        out.model.init_from = str(cont.path)
        out.trainer.max_epochs = int(cfg.trainer.max_epochs) - cont.epochs_before
    return out
