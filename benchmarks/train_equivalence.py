"""Same results? The loss curve of a recipe's first steps on this code against the run-to-run spread of another
code tree (the path before a speed change), one ``train.py`` process per run; prints JSON.

Runs ``python train.py`` of ``--old-code`` (a checkout, e.g. ``git worktree add /tmp/old COMMIT``) with ``data.seed``
= each of ``--seeds`` (its spread: the batches and augmentation draws differ), and of this repository with
``data.seed=--seeds[0]`` at each of ``--precisions``, all for ``--steps`` steps of ``--recipe`` (``NAME`` or
``NAME:sup`` / ``NAME:mix`` as in :mod:`benchmarks.train_step`), one torch thread each, ``--jobs`` at a time, and
reads every step's ``train/loss`` from the log. Reported: per window of ``--window`` steps the mean loss of every run,
the old runs' band (min, max), whether each new run's window means lie in the band widened by half its width, and
the mean over the last window.

    git worktree add /tmp/old HEAD~3
    python benchmarks/train_equivalence.py --recipe flow_allspeed:sup --old-code /tmp/old --steps 300
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.train_step import recipe_overrides  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
LOSS = re.compile(r"\] - step (\d+)\S* .*?train/loss=([0-9.eE+-]+)")


def run(code: Path, recipe: str, steps: int, seed: int, precision: str | None, init: str | None,
        runs_dir: Path, kitti: str) -> dict[int, float]:
    """``{step: train/loss}`` of one run of ``code``'s train.py."""
    over = [o for o in recipe_overrides(recipe, steps) if not o.startswith(("trainer.print_every", "model.init_from"))]
    over += [f"model.init_from={init}" if init else "model.init_from=null", f"data.seed={seed}", "threads=1",
             "trainer.print_every_n_steps=1", f"runs_dir={runs_dir}", f"name=s{seed}_{precision}"]
    if recipe.startswith("flow"):
        over.append(f"data.cache_dir={Path(os.environ.get('DFVO_RUNS_DIR', '~/dfvo-runs')).expanduser()}/render_cache")
    if precision:
        over.append(f"trainer.precision={precision}")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "DFVO_KITTI_RAW_ROOT": kitti}
    res = subprocess.run([sys.executable, "train.py", *over], cwd=code, capture_output=True, text=True, env=env)
    if res.returncode:
        raise RuntimeError(f"{code} {over}: exit {res.returncode}\n{res.stderr[-2000:]}")
    return {int(m.group(1)): float(m.group(2)) for m in LOSS.finditer(res.stdout + res.stderr)}


def windows(losses: dict[int, float], steps: int, width: int) -> list[float]:
    out = []
    for start in range(1, steps + 1, width):
        vals = [v for k, v in losses.items() if start <= k < start + width]
        out.append(sum(vals) / len(vals) if vals else float("nan"))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--recipe", required=True)
    p.add_argument("--old-code", type=Path, required=True)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--window", type=int, default=50)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--precisions", nargs="+", default=["auto", "32-true"])
    p.add_argument("--init", default=None, help="model.init_from of every run (default: none)")
    p.add_argument("--jobs", type=int, default=2)
    a = p.parse_args()
    kitti = os.environ.get("DFVO_KITTI_RAW_ROOT", str(REPO.parent / "shared" / "data" / "kitti_raw"))
    with tempfile.TemporaryDirectory() as tmp:
        jobs = {f"old data.seed={s}": (a.old_code, s, None) for s in a.seeds}
        jobs.update({f"new {prec} data.seed={a.seeds[0]}": (REPO, a.seeds[0], prec) for prec in a.precisions})
        with ThreadPoolExecutor(a.jobs) as pool:
            futures = {name: pool.submit(run, code, a.recipe, a.steps, seed, prec, a.init,
                                         Path(tmp) / re.sub(r"[^A-Za-z0-9_.-]", "_", name), kitti)
                       for name, (code, seed, prec) in jobs.items()}
            curves = {name: windows(f.result(), a.steps, a.window) for name, f in futures.items()}
    old = [c for n, c in curves.items() if n.startswith("old")]
    band = [(min(v), max(v)) for v in zip(*old)]
    verdict = {}
    for name, curve in curves.items():
        if name.startswith("new"):
            inside = [lo - (hi - lo) / 2 <= v <= hi + (hi - lo) / 2 for v, (lo, hi) in zip(curve, band)]
            verdict[name] = {"windows_in_band": sum(inside), "windows": len(inside), "last_window": curve[-1]}
    print(json.dumps({"recipe": a.recipe, "steps": a.steps, "window": a.window, "old_code": str(a.old_code),
                      "curves": {n: [round(v, 4) for v in c] for n, c in curves.items()},
                      "old_band": [[round(lo, 4), round(hi, 4)] for lo, hi in band], "verdict": verdict}, indent=1))


if __name__ == "__main__":
    main()
