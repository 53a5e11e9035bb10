"""Training entry: build the LightningModule of ``cfg.model.task``, the datamodule and the Trainer, and fit.

Registry: ``"depth" -> dfvo.training.depth_module.DepthPoseModule``, ``"flow" -> dfvo.training.flow_module.FlowModule``
(imported lazily; each built as ``Module(cfg)``). Outputs go to ``runs/<name>/``: ``checkpoints/last.ckpt`` and
``best-*.ckpt`` (monitored metric from ``cfg.model.monitor``), TensorBoard logs under ``runs/<name>/tb``.
``ckpt_path=...`` resumes exactly (weights, optimiser, scheduler, step, data position: the stateful train loader of
:mod:`dfvo.training.datamodule` skips the batches of the epoch already trained, also from a checkpoint written
mid-epoch, e.g. by a run stopped by ``trainer.max_steps``). Checkpoints record the task and model name; resuming
from a checkpoint of another model type stops with an error before training.
"""

from __future__ import annotations

import importlib
import math
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint, TQDMProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY, load_training_checkpoint
from dfvo.training.datamodule import DFVODataModule

MODULES: dict[str, str] = {
    "depth": "dfvo.training.depth_module:DepthPoseModule",
    "flow": "dfvo.training.flow_module:FlowModule",
}
REPO_ROOT = Path(__file__).resolve().parents[2]
if not OmegaConf.has_resolver("dfvo_repo"):
    # ${dfvo_repo:} in the configs: the repository root, so data roots default to <repo>/../shared/data/...
    OmegaConf.register_new_resolver("dfvo_repo", lambda: str(REPO_ROOT))


def _get(cfg: Any, key: str, default: Any) -> Any:
    value = OmegaConf.select(cfg, key, default=default)
    return default if value is None else value


def model_identity(cfg: DictConfig) -> str:
    """``"<task>:<name>"`` of ``cfg.model``, e.g. ``"depth:depth_stereo"``; stored in every checkpoint."""
    name = _get(cfg, "model.name", None) or _get(cfg, "model.mode", "?")
    return f"{_get(cfg, 'model.task', '?')}:{name}"


def build_module(cfg: DictConfig) -> L.LightningModule:
    """The LightningModule registered for ``cfg.model.task``."""
    task = _get(cfg, "model.task", None)
    if task not in MODULES:
        raise ValueError(f"model.task: expected one of {sorted(MODULES)}, got {task!r}")
    module_name, cls_name = MODULES[task].split(":")
    return getattr(importlib.import_module(module_name), cls_name)(cfg)


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


def check_checkpoint(path: str | Path, cfg: DictConfig) -> None:
    """Raise :class:`CheckpointError` if the checkpoint at ``path`` is missing, cannot be read, has no dfvo model
    identity, or was written for another model type than ``cfg.model``."""
    load_training_checkpoint(path, "ckpt_path", identity=model_identity(cfg))


def build_trainer(cfg: DictConfig, run_dir: Path) -> L.Trainer:
    """Trainer with checkpoints (last + best), LR monitor, progress bar, TensorBoard and the NaN guard."""
    t = cfg.trainer
    monitor = _get(cfg, "model.monitor", None)
    mode = str(_get(cfg, "model.monitor_mode", "min"))
    # "last" has its own callback: Lightning 2.6's save_last only rewrites last.ckpt when a top-k file was saved
    callbacks: list[Callback] = [
        ModelCheckpoint(dirpath=run_dir / "checkpoints", filename="last", monitor=None, save_top_k=1,
                        enable_version_counter=False),
        NaNGuard(), ModelIdentity(model_identity(cfg)), LoggedStepAfterResume(),
    ]
    if monitor:
        callbacks.append(ModelCheckpoint(dirpath=run_dir / "checkpoints", filename="best-{epoch}-{step}",
                                         monitor=monitor, mode=mode, save_top_k=1))
    if bool(_get(t, "enable_progress_bar", True)):
        callbacks.append(TQDMProgressBar(refresh_rate=int(_get(t, "progress_refresh", 10))))
    logger: Any = False
    if bool(_get(t, "logger", True)):
        logger = TensorBoardLogger(save_dir=str(run_dir), name="tb", version="")
        callbacks.append(LearningRateMonitor(logging_interval="step"))
    kwargs: dict[str, Any] = dict(
        accelerator=str(_get(t, "accelerator", "auto")), devices=_get(t, "devices", "auto"),
        strategy=str(_get(t, "strategy", "auto")), num_nodes=int(_get(t, "num_nodes", 1)),
        max_epochs=int(_get(t, "max_epochs", 20)), max_steps=int(_get(t, "max_steps", -1)),
        log_every_n_steps=int(_get(t, "log_every_n_steps", 10)),
        check_val_every_n_epoch=int(_get(t, "check_val_every_n_epoch", 1)),
        limit_train_batches=_get(t, "limit_train_batches", None),
        limit_val_batches=_get(t, "limit_val_batches", None),
        num_sanity_val_steps=int(_get(t, "num_sanity_val_steps", 0)),
        precision=_get(t, "precision", "32-true"), deterministic=bool(_get(t, "deterministic", False)),
        gradient_clip_val=_get(t, "gradient_clip_val", None),
        enable_progress_bar=bool(_get(t, "enable_progress_bar", True)),
        default_root_dir=str(run_dir), callbacks=callbacks, logger=logger,
        # the datamodule shards with its own resumable sampler; Lightning must not wrap it in a DistributedSampler
        use_distributed_sampler=False,
    )
    return L.Trainer(**kwargs)


def run_training(cfg: DictConfig) -> dict[str, Any]:
    """Train as ``cfg`` says; return the run directory, checkpoint paths and the last logged metrics.

    Args:
        cfg: composed config with groups ``model`` (task, name, ...), ``data``, ``trainer`` and top-level
            ``name`` (run name), ``runs_dir``, ``seed``, ``ckpt_path`` (resume) and ``threads``.
    """
    threads = int(_get(cfg, "threads", 0))
    if threads > 0:
        torch.set_num_threads(threads)
    L.seed_everything(int(_get(cfg, "seed", 0)), workers=True)
    run_dir = Path(str(_get(cfg, "runs_dir", "runs"))) / str(_get(cfg, "name", model_identity(cfg).replace(":", "_")))
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = _get(cfg, "ckpt_path", None)
    if ckpt_path:
        check_checkpoint(ckpt_path, cfg)
    datamodule = DFVODataModule(cfg)  # checks the data fits the model (e.g. supervised flow needs true flow)
    module = build_module(cfg)
    trainer = build_trainer(cfg, run_dir)
    if trainer.is_global_zero:
        (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    trainer.fit(module, datamodule=datamodule, ckpt_path=str(ckpt_path) if ckpt_path else None)
    ckpts = [c for c in trainer.callbacks if isinstance(c, ModelCheckpoint)]
    last = ckpts[0].best_model_path
    best = ckpts[1].best_model_path if len(ckpts) > 1 and ckpts[1].best_model_path else last
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()
               if torch.as_tensor(v).numel() == 1 and math.isfinite(float(v))}
    return {"run_dir": str(run_dir), "last_ckpt": last, "best_ckpt": best,
            "global_step": trainer.global_step, "metrics": metrics, "module": module}
