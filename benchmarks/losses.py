"""The photometric loss's cost: SSIM + L1 forward and backward (``dfvo.losses.photometric.ssim_l1_error``) on the views
of one training step, this tree against another checkout's, alternated in one process; prints JSON.

A depth step compares its target with ``--views`` warped views (source views x batch) at every scale, each upsampled to
the input (``--height`` x ``--width``); the target's moments are computed once (as the depth and flow losses do).
``--old-code DIR`` loads ``DIR/dfvo/losses/photometric.py`` beside this tree's under another module name, so both run
on the same tensors, the same allocator setting and the same machine load; the two alternate in ``--rounds`` rounds of
``--repeats`` calls and each reports its median.

    OMP_NUM_THREADS=1 python benchmarks/losses.py --old-code /tmp/old
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import statistics
import time
from pathlib import Path
from types import ModuleType

import torch

REPO = Path(__file__).resolve().parents[1]


def load_photometric(code: Path, name: str) -> ModuleType:
    """``code/dfvo/losses/photometric.py`` as a module named ``name`` (its imports: the installed packages)."""
    path = code / "dfvo" / "losses" / "photometric.py"
    if not path.is_file():
        raise SystemExit(f"--old-code {code}: {path} does not exist (expected a dfvo checkout)")
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def time_loss(module: ModuleType, target: torch.Tensor, warped: torch.Tensor, repeats: int) -> list[float]:
    """Seconds of ``repeats`` forward + backward calls of ``module.ssim_l1_error``, with the target's moments given
    where the module has ``ssim_moments`` (trees before `1d414ba` compute them in every call)."""
    views = warped.shape[0] // target.shape[0]
    target_all = target.repeat(views, 1, 1, 1)
    moments = None
    if hasattr(module, "ssim_moments"):
        moments = tuple(m.repeat(views, 1, 1, 1) for m in module.ssim_moments(target))
    times = []
    for _ in range(repeats):
        warped.grad = None
        start = time.perf_counter()
        error = module.ssim_l1_error(target_all, warped, 0.85, moments) if moments else module.ssim_l1_error(
            target_all, warped, 0.85)
        error.mean().backward()
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--old-code", type=Path, default=None, help="another dfvo checkout to compare with")
    p.add_argument("--views", type=int, default=12, help="warped views per call (source views x batch)")
    p.add_argument("--batch", type=int, default=4, help="targets per call (views must be a multiple)")
    p.add_argument("--height", type=int, default=96)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    if a.views % a.batch:
        raise SystemExit(f"--views {a.views} must be a multiple of --batch {a.batch}")
    torch.set_num_threads(a.threads)
    from dfvo.training.allocator import keep_freed_memory

    keep_freed_memory()  # as in training (trainer.keep_freed_memory)
    variants = {"this code": load_photometric(REPO, "photometric_this")}
    if a.old_code is not None:
        variants["old code"] = load_photometric(a.old_code.resolve(), "photometric_old")
    g = torch.Generator().manual_seed(0)
    target = torch.rand(a.batch, 3, a.height, a.width, generator=g)
    warped = torch.rand(a.views, 3, a.height, a.width, generator=g).requires_grad_(True)
    times: dict[str, list[float]] = {k: [] for k in variants}
    for r in range(a.rounds):
        for name in (list(variants) if r % 2 == 0 else list(reversed(variants))):
            times[name] += time_loss(variants[name], target, warped, a.repeats)
    out = {name: {"ms_median": round(statistics.median(t) * 1e3, 2), "calls": len(t)} for name, t in times.items()}
    if "old code" in out:
        out["speedup_vs_old_code"] = round(out["old code"]["ms_median"] / out["this code"]["ms_median"], 3)
    print(json.dumps({"machine": platform.machine(), "threads": a.threads, "torch": torch.__version__,
                      "cpu_capability": torch.backends.cpu.get_cpu_capability(), "views": a.views,
                      "size": [a.height, a.width], "old_code": str(a.old_code) if a.old_code else None,
                      "results": out}, indent=1))


if __name__ == "__main__":
    main()
