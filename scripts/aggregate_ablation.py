"""Collect infer.py runs (a multirun sweep folder, or several run folders) into a markdown ablation table.

Rows are the configurations (only the config groups, and the other command-line overrides such as
``flow.refine.iterations``, that vary across the runs are shown, like the paper's ablation table); columns are
sequences. A cell holds ``t_err % / r_err deg/100m`` when the sequence is long enough
for the KITTI metrics (>= 100 m), otherwise ``RPE m / ATE m``; the fallback rate of the run is added with
``--fallback``.

With ``--reference``, rows are labelled the way the paper's ablation table is: the reference configuration (the most
common value of every varying setting) is the row "reference", and every other row is named by the settings in which
it differs from it (``tracker=pnp``). Run one sweep per factor into sibling folders and aggregate them together.

Usage:
    python scripts/aggregate_ablation.py multirun/infer/2026-01-01_12-00-00 [more folders] [--out table.md]
        [--fallback] [--reference]

Each run folder must hold the ``summary.json`` that infer.py writes (with its ``metrics`` and ``choices``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dfvo.eval.ablation import load_runs, table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=None,
                        help="also write the table to this markdown file (missing folders are created)")
    parser.add_argument("--fallback", action="store_true", help="add the constant-motion fallback rate per cell")
    parser.add_argument("--reference", action="store_true",
                        help="name rows by how they differ from the most common configuration (paper layout)")
    args = parser.parse_args(argv)
    text = table(load_runs(args.folders), args.fallback, args.reference)
    if args.out is not None:
        try:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text)
        except OSError as err:
            blocker = next((d for d in args.out.parents if d.exists() and not d.is_dir()), None)
            reason = f"{blocker} is a file, not a folder" if blocker is not None else (err.strerror or str(err))
            parser.error(f"--out {args.out}: cannot write the table ({reason})")
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
