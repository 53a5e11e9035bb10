"""The ablation table of infer.py runs (dfvo.eval.ablation) and its command scripts/aggregate_ablation.py, on
hand-written run folders (the end-to-end sweep: test_infer.py::test_tiny_multirun_and_ablation_table)."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import pytest

from dfvo.eval.ablation import load_runs, table

REPO = Path(__file__).resolve().parents[2]


def test_aggregate_table_from_hand_written_runs(tmp_path: Path) -> None:
    def put(name: str, seq: str, tracker: str, metrics: dict) -> None:
        d = tmp_path / name
        d.mkdir()
        (d / "summary.json").write_text(json.dumps({
            "sequence": seq, "metrics": metrics, "fallback": {"constant_motion_rate": 0.25},
            "choices": {"tracker": tracker, "correspondence": "local_best_k"}}))

    put("a", "09", "hybrid", {"t_err_pct": 2.5, "r_err_deg_per_100m": 0.31, "rpe_m": 0.02, "ate_m": 5.0})
    put("b", "09", "pnp", {"t_err_pct": 4.0, "r_err_deg_per_100m": 0.5, "rpe_m": 0.03, "ate_m": 9.0})
    put("c", "10", "hybrid", {"t_err_pct": None, "r_err_deg_per_100m": None, "rpe_m": 0.0123, "ate_m": 0.456})
    text = table(load_runs([tmp_path]), fallback=True)
    lines = text.splitlines()
    assert "| tracker | 09 | 10 |" in lines
    assert "| hybrid | 2.50 / 0.31 (25% CM) | 0.0123 / 0.456 (25% CM) |" in lines
    assert "| pnp | 4.00 / 0.50 (25% CM) |  |" in lines


def test_aggregate_table_shows_varying_overrides(tmp_path: Path) -> None:
    """A swept key that is not a config group (``flow.refine.iterations=0,5``) becomes a column of the table."""
    for name, tracker, iters, rpe in (("a", "hybrid", "0", 1.2), ("b", "hybrid", "5", 0.15), ("c", "pnp", "5", 0.2)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps({
            "sequence": "06", "metrics": {"rpe_m": rpe, "ate_m": 1.0}, "choices": {"tracker": tracker},
            "overrides": {"flow.refine.iterations": iters}}))
    lines = table(load_runs([tmp_path])).splitlines()
    assert "| tracker | flow.refine.iterations | 06 |" in lines
    assert "| hybrid | 0 | 1.2 / 1 |" in lines and "| hybrid | 5 | 0.15 / 1 |" in lines
    # paper layout: the most common setting of each factor is the reference, other rows say what they change
    lines = table(load_runs([tmp_path]), reference=True).splitlines()
    assert "Reference: tracker=hybrid, flow.refine.iterations=5" in lines
    assert lines[3:] == ["| variant | 06 |", "|---|---|", "| reference | 0.15 / 1 |",
                         "| flow.refine.iterations=0 | 1.2 / 1 |", "| tracker=pnp | 0.2 / 1 |"]


def test_aggregate_out_creates_missing_folders(tmp_path: Path) -> None:
    main = runpy.run_path(str(REPO / "scripts" / "aggregate_ablation.py"))["main"]

    run = tmp_path / "runs" / "a"
    run.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps({"sequence": "09", "metrics": {"rpe_m": 0.1, "ate_m": 1.0},
                                                  "choices": {"tracker": "hybrid"}}))
    out = tmp_path / "missing" / "dir" / "table.md"
    assert main([str(tmp_path / "runs"), "--out", str(out)]) == 0
    assert "| tracker | 09 |" in out.read_text()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "runs"), "--out", str(tmp_path / "afile" / "table.md")])
    assert exc.value.code == 2
