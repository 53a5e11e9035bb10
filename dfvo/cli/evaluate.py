"""``dfvo-eval`` / ``python -m dfvo.evaluate``: evaluate trajectories (odometry), flow or depth.

    dfvo-eval gt_dir=GT pred_dir=PRED align=6dof|7dof|scale [format=auto|kitti|tum|euroc] [allow_prefix=true]
    dfvo-eval gt=GT_FILE pred=PRED_FILE align=7dof out=metrics.json
    dfvo-eval task=flow ... | task=depth ...

A Hydra app (``key=value`` overrides, ``--help`` for every key) on the config tree ``dfvo/conf/evaluate`` whose
typed schema is :class:`EvaluateConfig`. It creates no run folder and no log file: it writes only ``out=`` and
``plot_dir=``. Bad input ends with one ``error: ...`` line on stderr and exit status 2.
"""

from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import hydra
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf

from dfvo.cli.errors import run_reporting_errors
from dfvo.eval.report import evaluate_sequences, format_table, infer_run_align, resolve_align, sequence_name
from dfvo.io.json_io import write_json
from dfvo.io.trajectory import FORMATS
from dfvo.source_eval.config import DepthEvalConfig, FlowEvalConfig
from dfvo.source_eval.depth import evaluate_depth_task, format_depth_table
from dfvo.source_eval.flow import evaluate_flow_task, format_flow_table
from dfvo.validation import choice, one_of


class EvaluateTask(StrEnum):
    """What ``dfvo-eval`` evaluates (``task``)."""

    odometry = "odometry"
    flow = "flow"
    depth = "depth"


SCHEMA_NAME = "evaluate_schema"


@dataclass
class EvaluateConfig:
    """Every key of the evaluate command and its default (``evaluate.yaml`` only adds Hydra's settings).

    Attributes:
        task: ``odometry`` | ``flow`` | ``depth``.
        gt_dir: ground truth: a folder (all tasks), or for odometry a file or a dataset folder.
        pred_dir: predictions: a folder (all tasks), or for odometry one file.
        gt: one ground-truth trajectory file (odometry; instead of ``gt_dir``).
        pred: one predicted trajectory file (odometry; instead of ``pred_dir``).
        align: ``auto`` | ``6dof`` | ``7dof`` | ``scale`` | ``none``; ``auto``: the alignment ``infer.py`` used when
            the predictions are an ``infer.py`` run's (its ``metrics.json`` beside them says which), else ``7dof``.
        format: ``auto`` | ``kitti`` | ``tum`` | ``euroc`` of the files (``auto``: by content).
        gt_format: format of the ground truth when it differs from ``format`` (None: ``format``).
        seqs: sequence name or list of names (None: every prediction with ground truth); ints get two digits.
        exclude: sequences left out of the average.
        allow_prefix: evaluate a shorter line-by-line prediction against the first poses of the ground truth.
        max_time_diff: timestamp association tolerance (s).
        time_offset: added to predicted timestamps before association (s).
        gt_times: timestamps of the ground truth (KITTI ``times.txt`` file or a folder of them).
        out: JSON file for the results (None: print only).
        plot_dir: folder for trajectory / segment-error plots (None: no plots).
        flow: the settings of ``task=flow`` (:class:`dfvo.source_eval.config.FlowEvalConfig`).
        depth: the settings of ``task=depth`` (:class:`dfvo.source_eval.config.DepthEvalConfig`).
    """

    task: str = "odometry"
    gt_dir: str | None = None
    pred_dir: str | None = None
    gt: str | None = None
    pred: str | None = None
    align: str = "auto"
    format: str = "auto"
    gt_format: str | None = None
    seqs: Any = None
    exclude: Any = None
    allow_prefix: bool = False
    max_time_diff: float = 0.01
    time_offset: float = 0.0
    gt_times: str | None = None
    out: str | None = None
    plot_dir: str | None = None
    flow: FlowEvalConfig = field(default_factory=FlowEvalConfig)
    depth: DepthEvalConfig = field(default_factory=DepthEvalConfig)


def register_schema() -> None:
    """Register :class:`EvaluateConfig` as ``evaluate_schema`` in Hydra's ConfigStore, and the ``dfvo_user``
    resolver of its multirun folder (idempotent)."""
    ConfigStore.instance().store(name=SCHEMA_NAME, node=EvaluateConfig)
    OmegaConf.register_new_resolver("dfvo_user", _user_tag, replace=True)


def _user_tag() -> str:
    """``uUID`` of this process's user: ``-m``'s folder in the shared temp folder is per user (another user's
    ``dfvo-eval-multirun`` is not writable)."""
    return f"u{os.getuid()}" if hasattr(os, "getuid") else "user"


register_schema()


def _names(value: Any) -> list[str] | None:
    if value is None:
        return None
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value)
    items = value if isinstance(value, list | tuple) else [value]
    return [sequence_name(s) for s in items]


def odometry_options(cfg: DictConfig) -> dict:
    """The validated keyword arguments of :func:`dfvo.eval.report.evaluate_sequences` for ``cfg``.

    Raises:
        ValueError: a missing or contradictory path key or an unknown choice (one line naming the key).
    """
    paths = {}
    for file_key, dir_key in (("gt", "gt_dir"), ("pred", "pred_dir")):
        file_value, dir_value = cfg.get(file_key), cfg.get(dir_key)
        if file_value is not None and dir_value is not None:
            raise ValueError(f"both {file_key}={file_value} and {dir_key}={dir_value} are set; give one")
        if file_value is None and dir_value is None:
            raise ValueError(f"missing required argument {dir_key}=PATH (or {file_key}=FILE); "
                             "python -m dfvo.evaluate --help")
        paths[dir_key] = str(file_value if file_value is not None else dir_value)
    if cfg.max_time_diff < 0:
        raise ValueError(f"max_time_diff={cfg.max_time_diff}: expected seconds >= 0")
    return {
        **paths,
        "align": resolve_align(cfg.align, paths["pred_dir"]),
        "format": one_of(FORMATS, cfg.format, "format"),
        "gt_format": None if cfg.gt_format is None else one_of(FORMATS, cfg.gt_format, "gt_format"),
        "seqs": _names(cfg.seqs),
        "exclude": _names(cfg.exclude),
        "plot_dir": cfg.plot_dir,
        "allow_prefix": bool(cfg.allow_prefix),
        "max_time_diff": float(cfg.max_time_diff),
        "time_offset": float(cfg.time_offset),
        "gt_times": cfg.gt_times,
    }


def parse_args(argv: list[str]) -> dict:
    """Compose the config for ``argv`` (``key=value`` overrides) and return the odometry options plus ``out`` and
    ``task`` (for tests and scripts; the command itself goes through :func:`main`).

    Raises:
        ValueError: an unknown key, a bad value or a missing path (the message names the key).
    """
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="dfvo.conf.evaluate", version_base="1.3"):
            cfg = compose(config_name="evaluate", overrides=list(argv))
    except HydraException as exc:
        cause = f" ({exc.__cause__})" if exc.__cause__ is not None else ""
        raise ValueError(f"{exc}{cause}".replace("\n", " ")) from exc
    finally:
        GlobalHydra.instance().clear()
    return {"task": choice(EvaluateTask, cfg.task, "task").value, "out": cfg.out, **odometry_options(cfg)}


def _dispatch(cfg: DictConfig) -> dict:
    if cfg.task == "flow":
        result = evaluate_flow_task(cfg)
        print(format_flow_table(result))
        return result
    if cfg.task == "depth":
        result = evaluate_depth_task(cfg)
        print(format_depth_table(result))
        return result
    options = odometry_options(cfg)
    if str(cfg.align) == "auto":
        used, path = infer_run_align(options["pred_dir"])
        if used is not None:
            print(f"align=auto: {used}, the alignment infer.py reported this run with ({path}); align= to choose")
    with warnings.catch_warnings():  # the scale warning is printed once, under the table
        warnings.simplefilter("ignore", UserWarning)
        result = {"task": "odometry", **evaluate_sequences(options.pop("gt_dir"), options.pop("pred_dir"),
                                                           **options)}
    print(format_table(result))
    return result


def run(cfg: DictConfig) -> dict:
    """Evaluate for a composed config: dispatch on ``cfg.task``, write ``cfg.out`` (JSON) when set."""
    choice(EvaluateTask, cfg.task, "task")
    result = _dispatch(cfg)
    if cfg.out:
        print(f"wrote {write_json(cfg.out, result)}")
    return result


@hydra.main(config_path="pkg://dfvo.conf.evaluate", config_name="evaluate", version_base="1.3")
def evaluate_app(cfg: DictConfig) -> dict:
    """The Hydra task: :func:`run`, with bad input reported as one ``error:`` line and exit status 2."""
    try:
        return run(cfg)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    """Entry point of ``dfvo-eval`` and ``python -m dfvo.evaluate``: :func:`evaluate_app`, with a config Hydra cannot
    compose (an unknown key: the closest valid one; a missing quote) also one ``error:`` line, exit status 2."""
    run_reporting_errors(None, evaluate_app, None, exit_code=2)


if __name__ == "__main__":
    main()
