"""The flow shipping rule of issue 37 applied to panels of ``studies/length_panel.py``; prints JSON.

    python studies/flow_shipping_rule.py --base PANEL.json --shipped NAME --seeds NAME NAME NAME \\
        --candidates PANEL.json [PANEL.json ...]

Rule (true-length RPE, m, of every case: KITTI 06 at ``data.step`` 1, 2, 3, 07 at 1, 2, the four held-out synthetic
worlds): a candidate ships when (1) the geometric mean over all cases is lower than the shipped network's, (2) no
KITTI case is more than 5 % worse, and (3) no synthetic case is worse than the shipped network's by more than its
spread (max - min) over the three tracker seeds of ``--seeds`` (the shipped network's runs with ``tracker.seed=0,1,2``).
The RPE as run (with the tracker's own lengths) is reported beside it.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

KITTI = ("kitti06", "kitti06_step2", "kitti06_step3", "kitti07", "kitti07_step2")
SYNTHETIC = ("synthetic_drive", "synthetic_city", "synthetic_straight", "synthetic_highway")
KITTI_TOLERANCE = 0.05


def _rpe(run: dict[str, Any], kind: str) -> float:
    return float(run[kind]["rpe_m"])


def _geomean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values))


def judge(shipped: dict[str, Any], seeds: list[dict[str, Any]], candidate: dict[str, Any]) -> dict[str, Any]:
    """The rule's verdict for one candidate's runs (case -> panel record) against the shipped network's."""
    cases = [c for c in (*KITTI, *SYNTHETIC) if c in candidate and c in shipped]
    tl = {c: (_rpe(shipped[c], "true_lengths"), _rpe(candidate[c], "true_lengths")) for c in cases}
    run = {c: (_rpe(shipped[c], "as_run"), _rpe(candidate[c], "as_run")) for c in cases}
    failures = []
    for c in cases:
        old, new = tl[c]
        if c in KITTI and new > (1 + KITTI_TOLERANCE) * old:
            failures.append(f"{c}: {new:.4f} vs {old:.4f} ({new / old - 1:+.0%}, more than 5 % worse)")
        if c in SYNTHETIC:
            spread = max(_rpe(s[c], "true_lengths") for s in seeds) - min(_rpe(s[c], "true_lengths") for s in seeds)
            if new - old > spread:
                failures.append(f"{c}: {new:.4f} vs {old:.4f}, worse by {new - old:.4f} > seed spread {spread:.4f}")
    g_old, g_new = _geomean([v[0] for v in tl.values()]), _geomean([v[1] for v in tl.values()])
    if not g_new < g_old:
        failures.append(f"geometric mean {g_new:.4f} not below {g_old:.4f}")
    return {"cases": len(cases), "geomean_true_length": [round(g_old, 5), round(g_new, 5)],
            "geomean_as_run": [round(_geomean([v[0] for v in run.values()]), 5),
                               round(_geomean([v[1] for v in run.values()]), 5)],
            "true_length_rpe": {c: [round(a, 5), round(b, 5), f"{b / a - 1:+.1%}"] for c, (a, b) in tl.items()},
            "as_run_rpe": {c: [round(a, 5), round(b, 5)] for c, (a, b) in run.items()},
            "ships": not failures and len(cases) == len(KITTI) + len(SYNTHETIC), "failures": failures}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, required=True, help="panel.json holding the shipped network's runs")
    p.add_argument("--shipped", default="shipped", help="its configuration name (tracker seed 0)")
    p.add_argument("--seeds", nargs=3, default=["shipped", "seed1", "seed2"])
    p.add_argument("--candidates", nargs="+", type=Path, required=True, help="panel.json files of the candidates")
    args = p.parse_args()
    base = json.loads(args.base.read_text())["runs"]
    seeds = [base[s] for s in args.seeds]
    verdicts = {}
    for path in args.candidates:
        for name, runs in json.loads(path.read_text())["runs"].items():
            verdicts[name] = judge(base[args.shipped], seeds, runs)
    print(json.dumps(verdicts, indent=1))


if __name__ == "__main__":
    main()
