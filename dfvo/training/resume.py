"""Which checkpoint a training run starts from: ``resume=auto`` (continue the named run), ``resume=never`` (a new run).

A run lives in ``runs_dir/name/`` (``runs_dir`` may be outside the work tree, e.g. ``~/dfvo-runs`` for long runs that
outlive a session: docs/training.md). Its resumable checkpoints are ``checkpoints/last.ckpt`` (written atomically
every ``trainer.checkpoint_every_n_steps`` steps and on SIGTERM / SIGINT), ``checkpoints/previous.ckpt`` (the one
before it, kept by :class:`dfvo.training.export.LastCheckpoint`) and ``best-*.ckpt``. A finished run also holds
``finished.json`` (:func:`write_finished`).

- ``resume=auto``: the newest of them (modification time) that loads and was written for this model continues the
  run exactly, as ``ckpt_path=`` does; an unreadable one (a file cut by a power loss) is skipped with a warning and the
  next one is used; none: the run starts from step 0.
- ``resume=never`` (default): a new run; a folder that already holds a run's checkpoint is refused in one line (a
  second run would mix its checkpoints and logs with the first's), unless ``ckpt_path=`` names what to resume.
- ``ckpt_path=PATH``: exactly that checkpoint (with ``resume=auto`` too: the explicit path wins).
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY, CheckpointError, load_training_checkpoint
from dfvo.validation import choice

__all__ = ["ResumeMode", "ResumePoint", "FINISHED_NAME", "run_checkpoints", "find_resume_point", "resume_point",
           "write_finished", "read_finished"]

log = logging.getLogger("dfvo.training")

FINISHED_NAME = "finished.json"


class ResumeMode(StrEnum):
    """``train.py resume=``: ``auto`` continues the named run from its newest checkpoint (or starts it); ``never``
    starts a new run and refuses a folder that already holds one."""

    never = "never"
    auto = "auto"


@dataclass(frozen=True)
class ResumePoint:
    """The checkpoint a run resumes from: its path, ``global_step``, and the files skipped as unreadable."""

    path: Path
    step: int
    skipped: tuple[str, ...] = ()


def run_checkpoints(run_dir: str | Path) -> list[Path]:
    """The resumable checkpoints of a run folder, newest first (``last.ckpt``, ``previous.ckpt``, ``best-*.ckpt``;
    not the ``*.tmp`` of a write in progress)."""
    folder = Path(run_dir) / "checkpoints"
    if not folder.is_dir():
        return []
    found = [p for p in folder.glob("*.ckpt") if p.is_file()]
    return sorted(found, key=lambda p: (p.stat().st_mtime, p.name == "last.ckpt"), reverse=True)


def find_resume_point(run_dir: str | Path, identity: str) -> ResumePoint | None:
    """The newest checkpoint of ``run_dir`` that loads and holds a ``identity`` (``task:name``) model (None: no
    checkpoint at all). Unreadable files are skipped (named in :attr:`ResumePoint.skipped`).

    Raises:
        CheckpointError: the folder holds checkpoints, none of them usable (each reason named).
    """
    skipped: list[str] = []
    for path in run_checkpoints(run_dir):
        try:
            ckpt = load_training_checkpoint(path, "checkpoint")
        except CheckpointError as err:
            skipped.append(str(err))
            continue
        found = ckpt.get(MODEL_IDENTITY_KEY)
        if found != identity:
            raise CheckpointError(f"resume=auto: {run_dir} holds a {found!r} run ({path.name}), not a {identity!r} "
                                  "one; pass the matching model= or name=OTHER for a new run")
        return ResumePoint(path, int(ckpt.get("global_step", 0)), tuple(skipped))
    if skipped:
        raise CheckpointError(f"resume=auto: no usable checkpoint in {Path(run_dir) / 'checkpoints'}: "
                              + "; ".join(skipped))
    return None


def resume_point(run_dir: str | Path, identity: str, mode: str, ckpt_path: str | None) -> ResumePoint | None:
    """The checkpoint the run in ``run_dir`` starts from (None: step 0), as ``resume`` and ``ckpt_path`` say (module
    docstring); logs the decision.

    Raises:
        ValueError: ``resume=never`` in a folder that holds a run's checkpoint and no ``ckpt_path``.
        CheckpointError: ``ckpt_path`` or every checkpoint of the folder unusable.
    """
    mode = choice(ResumeMode, mode, "resume")
    if ckpt_path:
        ckpt = load_training_checkpoint(ckpt_path, "ckpt_path", identity=identity)
        return ResumePoint(Path(ckpt_path), int(ckpt.get("global_step", 0)))
    if mode == ResumeMode.never:
        existing = run_checkpoints(run_dir)
        if existing:
            raise ValueError(f"{run_dir} already holds a run ({existing[0].name}); resume=auto continues it, "
                             "name=OTHER starts a new run beside it (or delete the folder)")
        return None
    point = find_resume_point(run_dir, identity)
    for reason in point.skipped if point else ():
        log.warning("resume=auto: skipped %s", reason)
    if point is None:
        log.info("resume=auto: %s has no checkpoint; starting the run at step 0", run_dir)
    else:
        written = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(point.path.stat().st_mtime))
        log.info("resume=auto: resuming %s from %s (step %d, written %s)", run_dir, point.path, point.step, written)
    return point


def write_finished(run_dir: str | Path, step: int, last_ckpt: str | None) -> Path:
    """Mark a run that ended normally: ``RUN/finished.json`` with its last step, checkpoint and time (atomic)."""
    path = Path(run_dir) / FINISHED_NAME
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"step": int(step), "last_ckpt": last_ckpt,
                               "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}, indent=1) + "\n")
    os.replace(tmp, path)
    return path


def read_finished(run_dir: str | Path) -> dict | None:
    """``RUN/finished.json`` (None: the run has not finished, or the file is not valid JSON)."""
    try:
        return json.loads((Path(run_dir) / FINISHED_NAME).read_text())
    except (OSError, ValueError):
        return None
