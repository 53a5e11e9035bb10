"""Training entry: build the LightningModule named by ``cfg.model._target_``, the datamodule and the Trainer, and fit.

The model node's ``_target_`` (``dfvo.training.depth_module.DepthPoseModule`` for the depth schema,
``dfvo.training.flow_module.FlowModule`` for the flow schema) is imported and built as ``Module(cfg)`` with the whole
typed config. Outputs go to ``runs_dir/name/``: ``checkpoints/last.ckpt`` (resumable) and ``best-*.ckpt`` (the
metric ``cfg.model.monitor``), ``weights.safetensors`` (the network inference loads, fp16, refreshed with last.ckpt;
:mod:`dfvo.training.export`), ``config.yaml``, TensorBoard logs under ``tb/``. ``ckpt_path=...`` resumes exactly
(weights, optimiser, scheduler, step, data position, also from a checkpoint written mid-epoch, e.g. by a run
stopped by ``trainer.max_steps`` or by a signal). Checkpoints record the model identity ``task:name``; resuming from
a checkpoint of another model type stops with an error before training.

The data module is :class:`~dfvo.training.flow_data.FlowMixDataModule` for ``data=flow_mix`` (whose run is one
epoch of the phases' steps: ``trainer.max_epochs`` is set to 1), else :class:`~dfvo.training.datamodule.DFVODataModule`.
SIGTERM and SIGINT stop a run after the step in progress with ``last.ckpt`` written
(:mod:`dfvo.training.stop_signals`; :class:`~dfvo.training.stop_signals.TrainingInterrupted` is raised).
"""

from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import get_class
from lightning.pytorch.callbacks import Callback, LearningRateMonitor, ModelCheckpoint, TQDMProgressBar
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from dfvo.io.checkpoint import load_training_checkpoint
from dfvo.training.allocator import keep_freed_memory
from dfvo.training.callbacks import (
    ChannelsLast,
    ConsoleMetrics,
    LoggedStepAfterResume,
    ModelIdentity,
    NaNGuard,
    ValidateAtStop,
)
from dfvo.training.config import FlowMixTrainDataConfig, TrainerConfig, data_config, model_config, typed
from dfvo.training.continuation import continued_config, read_continuation
from dfvo.training.datamodule import DFVODataModule
from dfvo.training.export import WEIGHTS_NAME, KeepWeights, LastCheckpoint
from dfvo.training.flow_data import FlowMixDataModule
from dfvo.training.precision import resolve_precision
from dfvo.training.resume import FINISHED_NAME, resume_point, write_finished
from dfvo.training.stop_signals import StopOnSignal, TrainingInterrupted, stop_signals
from dfvo.training.weight_average import WeightAverage

__all__ = ["model_identity", "build_module", "build_datamodule", "check_checkpoint", "build_trainer", "run_folder",
           "run_training",
           "NaNGuard", "TrainingInterrupted"]

log = logging.getLogger("dfvo.training")


def model_identity(cfg: DictConfig) -> str:
    """``"<task>:<name>"`` of ``cfg.model``, e.g. ``"depth:depth_stereo"``; stored in every checkpoint."""
    return f"{cfg.model.task}:{cfg.model.name}"


def build_module(cfg: DictConfig) -> L.LightningModule:
    """The LightningModule ``cfg.model._target_``, built from the whole config (checked against its schema)."""
    model_config(cfg)  # one-line errors for bad model settings before anything is built
    target = str(cfg.model._target_)
    try:
        cls = get_class(target)
    except Exception as err:  # hydra raises ImportError or ValueError with a long chain
        raise ValueError(f"model._target_={target!r}: cannot be imported ({type(err).__name__})") from err
    if not (isinstance(cls, type) and issubclass(cls, L.LightningModule)):
        raise ValueError(f"model._target_={target!r} is not a LightningModule class")
    return cls(cfg)


def check_checkpoint(path: str | Path, cfg: DictConfig) -> None:
    """Raise :class:`CheckpointError` if the checkpoint at ``path`` is missing, cannot be read, has no dfvo model
    identity, or was written for another model type than ``cfg.model``."""
    load_training_checkpoint(path, "ckpt_path", identity=model_identity(cfg))


def build_datamodule(cfg: DictConfig) -> L.LightningDataModule:
    """The data module of ``cfg.data`` (checks that the data fits the model before anything is read)."""
    if isinstance(data_config(cfg), FlowMixTrainDataConfig):
        return FlowMixDataModule(cfg)
    return DFVODataModule(cfg)


def _check_accelerator(t: TrainerConfig) -> None:
    if str(t.accelerator).lower() in ("gpu", "cuda") and not torch.cuda.is_available():
        raise ValueError(f"trainer.accelerator={t.accelerator} needs a CUDA GPU and torch sees none; use "
                         "trainer=default (accelerator auto: CPU here)")


def build_trainer(cfg: DictConfig, run_dir: Path, has_validation: bool = True, one_epoch_run: bool = False,
                  stopper: StopOnSignal | None = None) -> L.Trainer:
    """Trainer with checkpoints (last + weights export, best), LR monitor, progress bar or console lines,
    TensorBoard, the NaN guard, validation at a ``max_steps`` stop, the channels-last layout and the stop on
    SIGTERM/SIGINT, as ``cfg.trainer`` says.

    Args:
        cfg: the training config. run_dir: the run folder.
        has_validation: whether the data gives validation batches (without, there is no ``best`` checkpoint: its
            metric would never exist).
        one_epoch_run: the data's one epoch is the whole run (``data=flow_mix``): ``max_epochs`` is 1.
        stopper: the signal callback of the run (None: a new one, installed only as a callback).
    """
    t: TrainerConfig = typed(cfg.trainer, TrainerConfig, "trainer")
    _check_accelerator(t)
    if t.float32_matmul_precision:
        torch.set_float32_matmul_precision(t.float32_matmul_precision)
    model = model_config(cfg)
    data = data_config(cfg)
    clip = getattr(model, "grad_clip_norm", None)
    if clip is not None and t.gradient_clip_val is not None:
        raise ValueError(f"model.grad_clip_norm={clip} and trainer.gradient_clip_val={t.gradient_clip_val}: set one "
                         "of them (model.grad_clip_norm=null to clip by the trainer's value)")
    identity = model_identity(cfg)
    weights = run_dir / WEIGHTS_NAME if t.export_weights else None
    last = LastCheckpoint(run_dir / "checkpoints", weights, size=(data.height, data.width), identity=identity,
                          every_n_steps=t.checkpoint_every_n_steps)
    stopper = stopper if stopper is not None else StopOnSignal()
    stopper.last = last
    callbacks: list[Callback] = [last, NaNGuard(), ModelIdentity(identity), LoggedStepAfterResume(), stopper]
    if t.ema_decay is not None:  # before the exports below: they write the average of this step
        callbacks.insert(0, WeightAverage(t.ema_decay))
    if model.monitor and has_validation:
        if t.keep_best:
            callbacks.append(ModelCheckpoint(dirpath=run_dir / "checkpoints", filename="best-{epoch}-{step}",
                                             monitor=model.monitor, mode=model.monitor_mode.value, save_top_k=1))
    elif model.monitor:
        log.warning("model.monitor=%s: data=%s gives no validation data (data.val_seeds=[] and no data.val_split), "
                    "so there is no best checkpoint; last.ckpt is written as usual", model.monitor, data.kind)
    if t.validate_at_stop:
        callbacks.append(ValidateAtStop())
    if t.channels_last:
        callbacks.append(ChannelsLast())
    if t.enable_progress_bar:
        callbacks.append(TQDMProgressBar(refresh_rate=t.progress_refresh))
    if t.print_every_n_steps > 0:
        callbacks.append(ConsoleMetrics(t.print_every_n_steps))
    if t.keep_weights_every_n_steps:
        callbacks.append(KeepWeights(run_dir, t.keep_weights_every_n_steps, size=(data.height, data.width),
                                     identity=identity))
    logger: Any = False
    if t.logger:
        logger = TensorBoardLogger(save_dir=str(run_dir), name="tb", version="")
        callbacks.append(LearningRateMonitor(logging_interval="step"))
    precision, why = resolve_precision(t.precision, t.accelerator)
    log.info("precision %s: %s", precision, why)
    max_epochs = t.max_epochs
    if one_epoch_run and max_epochs != 1:
        log.info("data=%s: one epoch is the whole run (the steps of model.phases); trainer.max_epochs=1", data.kind)
        max_epochs = 1
    return L.Trainer(
        accelerator=t.accelerator, devices=t.devices, strategy=t.strategy, num_nodes=t.num_nodes,
        max_epochs=max_epochs, max_steps=t.max_steps, log_every_n_steps=t.log_every_n_steps,
        check_val_every_n_epoch=t.check_val_every_n_epoch, val_check_interval=t.val_check_interval,
        limit_train_batches=t.limit_train_batches,
        limit_val_batches=t.limit_val_batches, num_sanity_val_steps=t.num_sanity_val_steps, precision=precision,
        deterministic=t.deterministic, gradient_clip_val=t.gradient_clip_val, benchmark=t.benchmark,
        enable_progress_bar=t.enable_progress_bar, default_root_dir=str(run_dir), callbacks=callbacks,
        logger=logger, enable_model_summary=False,
        # the datamodule shards with its own resumable sampler; Lightning must not wrap it in a DistributedSampler
        use_distributed_sampler=False,
    )


class _NoAdverts(logging.Filter):
    """Drop Lightning's product adverts ("💡 Tip: ... try installing [litlogger] ...") from its log."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.getMessage()).lstrip().startswith("💡")


def quiet_lightning_output() -> None:
    """One copy of each Lightning line, no adverts, no deprecation notices users cannot act on.

    ``import lightning`` gives its logger a console handler of its own while the records also propagate to the root
    logger (which Hydra configures: console and the run's log file), so every line was printed twice; with a
    configured root logger the own handler is removed. Lightning's "💡 Tip" adverts are filtered out, and the
    deprecation warning Lightning 2.6 triggers in torch's pytree on every run (``isinstance(treespec, LeafSpec)``)
    is ignored. Idempotent."""
    root = logging.getLogger()
    package = logging.getLogger("lightning")
    if root.handlers:
        for handler in list(package.handlers):
            if type(handler) is logging.StreamHandler:
                package.removeHandler(handler)
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        target = logging.getLogger(name)
        if not any(isinstance(f, _NoAdverts) for f in target.filters):
            target.addFilter(_NoAdverts())
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)` is deprecated")
    # a run folder with checkpoints is either resumed (resume=auto, ckpt_path=) or refused (resume=never) before
    # Lightning sees it, so its "exists and is not empty" notice only repeats what the log already says
    warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")


def run_folder(cfg: DictConfig) -> Path:
    """``runs_dir/name`` (``~`` expanded)."""
    return Path(str(cfg.runs_dir)).expanduser() / str(cfg.name)


def _fit(cfg: DictConfig, stopper: StopOnSignal) -> tuple[L.Trainer, L.LightningModule, Path]:
    if cfg.threads > 0:
        torch.set_num_threads(int(cfg.threads))
    if cfg.trainer.keep_freed_memory:
        log.info(keep_freed_memory()[1])
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    run_dir = run_folder(cfg)
    start = resume_point(run_dir, model_identity(cfg), str(cfg.get("resume", "never")), cfg.ckpt_path)
    ckpt_path = str(start.path) if start is not None else None
    continuation = read_continuation(cfg, model_identity(cfg))
    if continuation is not None:  # a run whose checkpoints were lost, continued from its weights
        cfg = continued_config(cfg, continuation)
        log.info("continue_from=%s: the run continues after step %d (epoch %d): %d epochs to go%s",
                 continuation.path, continuation.steps_before, continuation.epochs_before, cfg.trainer.max_epochs,
                 f", resumed from {ckpt_path}" if ckpt_path else "; depth network from these weights, the pose "
                 "network and the optimiser anew")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / FINISHED_NAME).unlink(missing_ok=True)  # written again when this run ends normally
    datamodule = build_datamodule(cfg)  # checks the data fits the model (e.g. supervised flow needs true flow)
    module = build_module(cfg)
    if continuation is not None:
        module.steps_before, module.epochs_before = continuation.steps_before, continuation.epochs_before
    trainer = build_trainer(cfg, run_dir, has_validation=datamodule.has_validation,
                            one_epoch_run=getattr(datamodule, "one_epoch_run", False), stopper=stopper)
    if trainer.is_global_zero:
        (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path)
    except TrainingInterrupted as err:
        raise stopper.interrupted(err.step) or err from None
    except BaseException as err:  # Lightning's SIGTERMException, a loader worker killed by the same signal, ...
        stopped = stopper.interrupted(int(trainer.global_step))
        if stopped is not None:
            raise stopped from err
        raise
    return trainer, module, run_dir


def run_training(cfg: DictConfig) -> dict[str, Any]:
    """Train as ``cfg`` says; return the run folder, checkpoint and weights paths, the step and the last metrics.

    Args:
        cfg: the composed training config (:class:`dfvo.training.config.TrainConfig`: groups ``model``, ``data``,
            ``trainer`` and ``name``, ``runs_dir``, ``seed``, ``ckpt_path``, ``resume``, ``threads``).

    Returns:
        ``run_dir``, ``last_ckpt``, ``best_ckpt`` (``last_ckpt`` when there is no best), ``weights`` (the exported
        ``weights.safetensors`` or None), ``global_step``, ``metrics`` (finite scalars), ``module``.

    Raises:
        TrainingInterrupted: SIGTERM or SIGINT stopped the run (``last.ckpt`` written when training had started).
    """
    quiet_lightning_output()
    stopper = StopOnSignal()
    with stop_signals(stopper):
        trainer, module, run_dir = _fit(cfg, stopper)
    last_cb = next(c for c in trainer.callbacks if isinstance(c, LastCheckpoint))
    best_cb = [c for c in trainer.callbacks if isinstance(c, ModelCheckpoint) and not isinstance(c, LastCheckpoint)]
    last = last_cb.best_model_path
    best = best_cb[0].best_model_path if best_cb and best_cb[0].best_model_path else last
    weights = last_cb.weights_path if last_cb.weights_path is not None and last_cb.weights_path.is_file() else None
    if trainer.is_global_zero:
        write_finished(run_dir, trainer.global_step, last or None)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()
               if torch.as_tensor(v).numel() == 1 and math.isfinite(float(v))}
    return {"run_dir": str(run_dir), "last_ckpt": last, "best_ckpt": best, "weights": str(weights) if weights else None,
            "global_step": trainer.global_step, "metrics": metrics, "module": module}
