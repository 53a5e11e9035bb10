"""An exponential moving average of the exported network's weights (``trainer.ema_decay``).

A long run at a constant learning rate wanders: the campaign's ``depth_scene`` network put KITTI 07's road at 1.632,
1.825 and 1.722 m at steps 2000, 3000 and 4000 (true 1.65), while the average of those three checkpoints' weights
was as accurate against LiDAR as each of them and steadier on the road (docs/training.md). With ``trainer.ema_decay=d``
the run keeps ``avg <- d avg + (1 - d) w`` of the network that inference loads (``module.export_network()``: its
parameters and buffers, batch-norm statistics included) after every optimiser step, and every export
(``weights.safetensors``, ``weights_step{N}.safetensors``) writes the average instead of the raw weights. The
average is part of the training checkpoint (this callback's state), so a resumed run continues it exactly; a run
resumed from a checkpoint written without it starts the average from the weights it resumes with (logged). The
validation metrics and ``best-*.ckpt`` stay those of the raw weights. There is no warm-up: the first update copies
the weights, so after ``n`` steps the weights of that first step still carry ``d**n`` of the average (0.999: 37 %
after 1000 steps, 5 % after 3000). Integer buffers (batch norm's ``num_batches_tracked``) are averaged too and
are meaningless in the export (inference does not read them). Half-precision training (``bf16-true``, ``16-true``)
is refused with it (:class:`dfvo.training.config.TrainerConfig`).
"""

from __future__ import annotations

import logging
from typing import Any

import lightning as L
import torch
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

__all__ = ["WeightAverage", "averaged_network"]

log = logging.getLogger("dfvo.training")


class WeightAverage(L.Callback):
    """Keeps the moving average (see the module docstring) of ``pl_module.export_network()[0]``.

    Args:
        decay: the average's decay per optimiser step, in (0, 1) (0.999: about the last 1000 steps).
    """

    def __init__(self, decay: float) -> None:
        if not 0.0 < float(decay) < 1.0:
            raise ValueError(f"trainer.ema_decay={decay}; expected a decay in (0, 1), e.g. 0.999, or null (off)")
        self.decay = float(decay)
        self.average: AveragedModel | None = None
        self._loaded: dict[str, Any] | None = None

    @property
    def state_key(self) -> str:
        return f"WeightAverage[decay={self.decay}]"

    def _network(self, pl_module: L.LightningModule) -> torch.nn.Module:
        return pl_module.export_network()[0]

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        net = self._network(pl_module)
        self.average = AveragedModel(net, multi_avg_fn=get_ema_multi_avg_fn(self.decay), use_buffers=True)
        if self._loaded is not None:
            self.average.load_state_dict(self._loaded)
            self._loaded = None
        elif getattr(trainer, "ckpt_path", None):  # the loop's step is restored after this hook: name the file
            log.info("trainer.ema_decay=%g: %s holds no weight average of this decay; it starts from the weights "
                     "resumed", self.decay, trainer.ckpt_path)
        pl_module.weight_average = self

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        if self.average is not None:
            self.average.update_parameters(self._network(pl_module))

    def state_dict(self) -> dict[str, Any]:
        return {"average": self.average.state_dict()} if self.average is not None else {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if "average" in state_dict:
            self._loaded = state_dict["average"]


def averaged_network(module: L.LightningModule) -> torch.nn.Module | None:
    """The averaged copy of ``module``'s exported network when a :class:`WeightAverage` keeps one, else None."""
    keeper = getattr(module, "weight_average", None)
    return keeper.average.module if isinstance(keeper, WeightAverage) and keeper.average is not None else None
