"""Training speed per recipe: milliseconds per real ``train.py`` step, and the speed-up of the default arithmetic
against float32 eager, in one process; prints JSON.

Each (recipe, precision) runs :func:`dfvo.training.runner.run_training` — the same code as ``python train.py
experiment=RECIPE`` — for ``--warmup + --steps`` steps (no validation, no checkpoint, no TensorBoard: what a step of
a long run costs between them) and times every step from the end of the previous one (data, forward, backward,
optimiser, Lightning's own work). ``ms_per_step`` is the median of the timed steps after the warm-up, ``steps_per_hour``
its inverse. The variants alternate in ``--rounds`` rounds (A B, B A, ...) so all see the same machine load; the
``speedup_vs_fp32`` of each is the median over rounds of (ms of ``32-true``) / (its ms). ``--old-code DIR`` adds
another checkout's code at its own defaults (``speedup_vs_old_code``: the before/after of a change), timed the same
way in a subprocess that imports ``dfvo`` from ``DIR``.

Recipes (``--recipes``): an experiment name, or ``NAME:PHASE`` for one phase of a step-scheduled flow recipe
(``flow_allspeed:sup``, ``flow_allspeed:mix``). Initial weights are left out (``model.init_from=null``: the speed does
not depend on them). KITTI raw: ``--kitti-raw`` or ``$DFVO_KITTI_RAW_ROOT``, else ``../shared/data/kitti_raw``.
Render caches: ``--runs-dir`` (default ``$DFVO_RUNS_DIR`` or ``~/dfvo-runs``), whose ``render_cache`` a campaign
shares.

    OMP_NUM_THREADS=1 python benchmarks/train_step.py --threads 1
    OMP_NUM_THREADS=1 python benchmarks/train_step.py --recipes flow_allspeed:sup --precisions 32-true auto
    OMP_NUM_THREADS=1 python benchmarks/train_step.py --recipes depth_small --precisions auto --old-code OLD --steady
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[1]
DEFAULT_RECIPES = ["depth_stage2", "flow_allspeed:sup", "flow_allspeed:mix"]


class StepTimer(L.Callback):
    """Wall seconds of every training step, from the end of the previous one (the first from the start of training).

    ``steady``: read every training sample once before the clock starts, as a long run's first epoch does (the
    synthetic frames a depth recipe keeps, ``data.keep_frames``, are then rendered): the steps of the epochs after."""

    def __init__(self, steady: bool = False) -> None:
        self.times: list[float] = []
        self._last: float | None = None
        self.steady = steady

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.steady:
            data = trainer.datamodule.train_set
            for i in range(len(data)):
                data[i]
        self._last = time.perf_counter()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        now = time.perf_counter()
        if self._last is not None:
            self.times.append(now - self._last)
        self._last = now


def recipe_overrides(recipe: str, steps: int) -> list[str]:
    """``train.py`` overrides of ``recipe`` (``NAME`` or ``NAME:PHASE``) for a ``steps``-step timing run."""
    name, _, phase = recipe.partition(":")
    out = [f"experiment={name}", "model.init_from=null", f"trainer.max_steps={steps}", "trainer.logger=false",
           "trainer.export_weights=false", "trainer.keep_best=false", "trainer.enable_progress_bar=false",
           "trainer.print_every_n_steps=0", "trainer.validate_at_stop=false", "trainer.limit_val_batches=0",
           "trainer.val_check_interval=null", "trainer.checkpoint_every_n_steps=null", "model.log_images_every=0"]
    if phase == "sup":
        out.append(f"model.phases=[{{name:sup,steps:{steps},lr:5.0e-5}}]")
    elif phase == "mix":
        out.append(f"model.phases=[{{name:mix,steps:{steps},lr:2.0e-5,kitti:true}}]")
    elif phase:
        raise SystemExit(f"--recipes {recipe}: phase {phase!r}; expected sup or mix")
    return out


def time_recipe(recipe: str, precision: str, steps: int, warmup: int, threads: int, runs_dir: Path,
                steady: bool = False) -> list[float]:
    """Per-step seconds of ``steps`` timed steps after ``warmup`` steps of ``recipe`` at ``precision``, in this
    process, with the ``dfvo`` that ``import dfvo`` finds (the step timer joins every Lightning Trainer built). A
    recipe that distils from a teacher (``model.teacher``) reads it from ``runs_dir`` as the campaign does."""
    from dfvo.training.runner import run_training

    timer = StepTimer(steady)
    init = L.Trainer.__init__

    def with_timer(self: L.Trainer, *args: Any, **kwargs: Any) -> None:
        kwargs["callbacks"] = [*(kwargs.get("callbacks") or []), timer]
        init(self, *args, **kwargs)

    with tempfile.TemporaryDirectory() as tmp:
        overrides = [*recipe_overrides(recipe, warmup + steps), f"threads={threads}", f"runs_dir={tmp}"]
        if precision != "code default":
            overrides.append(f"trainer.precision={precision}")
        if recipe.startswith("flow"):
            overrides.append(f"data.cache_dir={runs_dir / 'render_cache'}")
        with initialize_config_module("dfvo.conf.train", version_base="1.3"):
            teacher = OmegaConf.select(compose("train", overrides=[*overrides, f"runs_dir={runs_dir}"]),
                                       "model.teacher", default=None)
            if teacher and recipe.endswith(":sup"):  # a flow teacher supervises KITTI pairs: none in this phase
                overrides += ["model.teacher=null", "model.w_distill=0"]
            elif teacher:
                overrides.append(f"model.teacher={teacher}")
            cfg = compose("train", overrides=overrides)
        L.Trainer.__init__ = with_timer  # type: ignore[method-assign]
        try:
            run_training(cfg)
        finally:
            L.Trainer.__init__ = init  # type: ignore[method-assign]
    return timer.times[warmup:]


def time_other_code(code: Path, recipe: str, steps: int, warmup: int, threads: int, runs_dir: Path,
                    steady: bool = False) -> list[float]:
    """:func:`time_recipe` of another checkout's ``dfvo`` (its own default precision), in a subprocess."""
    cmd = [sys.executable, __file__, "--worker", recipe, "--steps", str(steps), "--warmup", str(warmup),
           "--threads", str(threads), "--runs-dir", str(runs_dir), *(["--steady"] if steady else [])]
    env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": str(threads)}
    res = subprocess.run(cmd, cwd=code, capture_output=True, text=True, env=env)
    if res.returncode:
        raise RuntimeError(f"{code}: {recipe}: exit {res.returncode}\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--recipes", nargs="+", default=DEFAULT_RECIPES)
    p.add_argument("--precisions", nargs="+", default=["32-true", "auto"])
    p.add_argument("--old-code", type=Path, default=None,
                   help="also time this checkout (e.g. `git worktree add /tmp/old COMMIT`) at its own defaults")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--runs-dir", type=Path,
                   default=Path(os.environ.get("DFVO_RUNS_DIR", "~/dfvo-runs")).expanduser())
    p.add_argument("--kitti-raw", type=Path, default=None)
    p.add_argument("--steady", action="store_true",
                   help="read every training sample once before timing: the steps after a long run's first epoch")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    a = p.parse_args()
    root = a.kitti_raw or Path(os.environ.get("DFVO_KITTI_RAW_ROOT", REPO.parent / "shared" / "data" / "kitti_raw"))
    os.environ["DFVO_KITTI_RAW_ROOT"] = str(root)
    torch.set_num_threads(a.threads)
    if a.worker:  # one timing of the dfvo on PYTHONPATH, for --old-code
        print(json.dumps(time_recipe(a.worker, "code default", a.steps, a.warmup, a.threads, a.runs_dir, a.steady)))
        return
    from dfvo.training.precision import cpu_has_bf16, resolve_precision  # not in an --old-code worker's dfvo

    variants = list(a.precisions) + (["old code"] if a.old_code else [])
    results: dict[str, Any] = {}
    for recipe in a.recipes:
        runs: dict[str, list[float]] = {v: [] for v in variants}
        for r in range(a.rounds):
            for v in (variants if r % 2 == 0 else list(reversed(variants))):
                times = (time_other_code(a.old_code, recipe, a.steps, a.warmup, a.threads, a.runs_dir, a.steady)
                         if v == "old code" else time_recipe(recipe, v, a.steps, a.warmup, a.threads, a.runs_dir,
                                                             a.steady))
                runs[v].append(statistics.median(times) * 1e3)
        entry: dict[str, Any] = {}
        for v, ms in runs.items():
            entry[v] = {"ms_per_step": round(min(ms), 1), "ms_per_step_rounds": [round(m, 1) for m in ms],
                        "steps_per_hour": round(3.6e6 / min(ms))}
            if v != "old code":
                entry[v]["resolved"] = resolve_precision(v, "cpu")[0]
            for base in ("32-true", "old code"):
                if base in runs and v != base:
                    ratios = [b / m for b, m in zip(runs[base], ms)]
                    entry[v][f"speedup_vs_{base.replace(' ', '_').replace('32-true', 'fp32')}"] = round(
                        statistics.median(ratios), 3)
        results[recipe] = entry
        print(json.dumps({recipe: entry}), flush=True)
    print(json.dumps({
        "machine": platform.processor() or platform.machine(), "cpu_bf16": cpu_has_bf16(), "threads": a.threads,
        "torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "old_code": str(a.old_code) if a.old_code else None, "steps_timed": a.steps, "warmup": a.warmup,
        "rounds": a.rounds, "steady": a.steady, "load_avg_1min": os.getloadavg()[0], "recipes": results}, indent=1))


if __name__ == "__main__":
    main()
