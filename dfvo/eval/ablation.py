"""The paper-style ablation table of infer.py runs (a multirun sweep folder, or several run folders), in Markdown.

Rows are the configurations (only the config groups, and the other command-line overrides such as
``flow.refine.iterations``, that vary across the runs are shown, like the paper's ablation table); columns are
sequences. A cell holds ``t_err % / r_err deg/100m`` when the sequence is long enough for the KITTI metrics (>= 100 m),
otherwise ``RPE m / ATE m``; the fallback rate of the run is added with ``fallback``.

With ``reference``, rows are labelled the way the paper's ablation table is: the reference configuration (the most
common value of every varying setting) is the row "reference", and every other row is named by the settings in which
it differs from it (``tracker=pnp``).

Each run folder must hold the ``summary.json`` that infer.py writes (with its ``metrics`` and ``choices``). The command
is ``scripts/aggregate_ablation.py``; ``scripts/results_tables.py`` renders the README's ablation tables with it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["GROUPS", "load_runs", "cell", "table"]

GROUPS = ("data", "tracker", "correspondence", "scale", "model_selection", "img_res", "flow", "depth")


def load_runs(folders: list[Path]) -> list[dict[str, Any]]:
    """Every ``summary.json`` under ``folders`` (recursively), newest layout first."""
    runs = []
    for folder in folders:
        if not folder.exists():
            raise FileNotFoundError(f"aggregate_ablation: {folder} does not exist (expected an infer.py output "
                                    f"or multirun folder)")
        for path in sorted(folder.rglob("summary.json")):
            summary = json.loads(path.read_text())
            summary["_path"] = str(path.parent)
            runs.append(summary)
    return runs


def cell(summary: dict[str, Any], fallback: bool) -> str:
    """One table cell: KITTI t_err/r_err when defined, else RPE/ATE; '-' without ground truth."""
    m = summary.get("metrics") or {}
    if m.get("t_err_pct") is not None and m.get("r_err_deg_per_100m") is not None:
        text = f"{m['t_err_pct']:.2f} / {m['r_err_deg_per_100m']:.2f}"
    elif m.get("rpe_m") is not None:
        text = f"{m['rpe_m']:.3g} / {m.get('ate_m', float('nan')):.3g}"
    else:
        text = "-"
    if fallback:
        rate = (summary.get("fallback") or {}).get("constant_motion_rate")
        text += f" ({100 * rate:.0f}% CM)" if rate is not None else ""
    return text


def table(runs: list[dict[str, Any]], fallback: bool = False, reference: bool = False) -> str:
    """Markdown table: one row per configuration, one column per sequence (``reference``: rows named by how they
    differ from the most common configuration, see the module docstring)."""
    if not runs:
        raise ValueError("aggregate_ablation: no summary.json found (did the runs finish?)")
    for r in runs:  # one namespace: group choices, then the other overrides (a group wins a name clash)
        r["_settings"] = {**{k: str(v) for k, v in (r.get("overrides") or {}).items()}, **r.get("choices", {})}
    overridden = sorted({k for r in runs for k in (r.get("overrides") or {})} - set(GROUPS))
    groups = [g for g in (*GROUPS, *overridden) if any(g in r["_settings"] for r in runs)]
    varying = [g for g in groups if len({r["_settings"].get(g) for r in runs}) > 1] or groups[:1]
    sequences = sorted({r["sequence"] for r in runs})
    long_metric = any((r.get("metrics") or {}).get("t_err_pct") is not None for r in runs)
    rows: dict[tuple[str, ...], dict[str, str]] = {}
    for r in runs:
        key = tuple(str(r["_settings"].get(g, "")) for g in varying)
        rows.setdefault(key, {})[r["sequence"]] = cell(r, fallback)
    unit = "t_err (%) / r_err (deg/100m)" if long_metric else "RPE (m) / ATE (m)"
    legend = f"Cells: {unit}" + ("; (CM) = constant-motion fallback rate" if fallback else "")
    if reference:
        return _reference_table(rows, varying, sequences, legend)
    head = "| " + " | ".join(varying + sequences) + " |"
    sep = "|" + "|".join(["---"] * (len(varying) + len(sequences))) + "|"
    lines = [legend, "", head, sep]
    for key in sorted(rows):
        lines.append("| " + " | ".join(list(key) + [rows[key].get(s, "") for s in sequences]) + " |")
    return "\n".join(lines) + "\n"


def _reference_table(rows: dict[tuple[str, ...], dict[str, str]], varying: list[str], sequences: list[str],
                     legend: str) -> str:
    """Rows named by their difference from the most common value of each varying setting; reference first."""
    from collections import Counter

    common = [Counter(key[i] for key in rows).most_common(1)[0][0] for i in range(len(varying))]
    reference = ", ".join(f"{g}={v}" for g, v in zip(varying, common) if v)
    named = []
    for key, cells in rows.items():
        diff = [f"{g}={v}" for g, v, c in zip(varying, key, common) if v != c]
        named.append((bool(diff), ", ".join(diff) or "reference", cells))
    lines = [legend, f"Reference: {reference}", "", "| variant | " + " | ".join(sequences) + " |",
             "|" + "|".join(["---"] * (1 + len(sequences))) + "|"]
    for _, name, cells in sorted(named):
        lines.append(f"| {name} | " + " | ".join(cells.get(s, "") for s in sequences) + " |")
    return "\n".join(lines) + "\n"
