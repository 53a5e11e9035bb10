"""The ``python -m dfvo.evaluate`` command (a Hydra app: folders or single files, formats, prefixes, task dispatch, no
files in the working directory), ``evaluate_sequences`` (JSON, average, exclude) and the plots."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dfvo.eval import evaluate_sequences, evaluate_trajectory, plot_segment_errors, plot_trajectory, write_kitti_poses
from dfvo.evaluate import parse_args

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def eval_cli(tool_cli):
    """``python -m dfvo.evaluate ARGS`` as a user runs it, from the folder ``cwd`` (exit status, stderr, the files it
    leaves): the ``tool_cli`` runner of tests/conftest.py (the module's ``main`` in this process)."""

    def run(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
        return tool_cli(cwd, "dfvo/evaluate.py")(*args, check=False)

    return run


def evaluate_in_process(*args: str) -> dict:
    """The command's work for ``ARGS`` in this process (:func:`dfvo.cli.evaluate.run` on the composed config: what it
    prints and writes); for the success paths, where a subprocess would only add the start-up of Python and torch."""
    from hydra import compose, initialize_config_module

    from dfvo.cli.evaluate import run

    with initialize_config_module(config_module="dfvo.conf.evaluate", version_base="1.3"):
        return run(compose(config_name="evaluate", overrides=list(args)))


def _line(n: int, step: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = np.arange(n) * step
    poses[:, 0, 3] = np.sin(np.arange(n) / 30.0) * 5
    return poses


@pytest.fixture
def folders(tmp_path: Path) -> tuple[Path, Path]:
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    for seq, n, drift in (("01", 300, 1.02), ("09", 250, 1.05), ("10", 60, 1.0)):
        gt = _line(n, 1.0)
        pred = gt.copy()
        pred[:, :3, 3] *= drift
        pred[:, 1, 3] += np.linspace(0, 3, n)
        write_kitti_poses(gt_dir / f"{seq}.txt", gt)
        write_kitti_poses(pred_dir / f"{seq}.txt", pred)
    return gt_dir, pred_dir


def test_parse_args_keeps_leading_zeros() -> None:
    args = parse_args(["gt_dir=a", "pred_dir=b", "seqs=[09,10]", "exclude=[01]", "align=6dof"])
    assert args["seqs"] == ["09", "10"] and args["exclude"] == ["01"] and args["align"] == "6dof"
    with pytest.raises(ValueError, match="gt_dir"):
        parse_args(["pred_dir=b"])
    with pytest.raises(ValueError, match="bogus"):
        parse_args(["gt_dir=a", "pred_dir=b", "bogus=1"])


def test_evaluate_sequences_average_and_exclude(folders, tmp_path: Path) -> None:
    gt_dir, pred_dir = folders
    res = evaluate_sequences(gt_dir, pred_dir, None, "none", exclude=["01"], plot_dir=tmp_path / "plots")
    assert list(res["sequences"]) == ["01", "09", "10"] and res["align"] == "none"
    assert res["sequences"]["10"]["t_err_pct"] is None  # 60 m: shorter than the shortest segment
    assert res["average"]["sequences"] == ["09", "10"]
    assert res["average"]["t_err_pct"] == pytest.approx(res["sequences"]["09"]["t_err_pct"])
    ate = [res["sequences"][s]["ate_m"] for s in ("09", "10")]
    assert res["average"]["ate_m"] == pytest.approx(np.mean(ate))
    direct = evaluate_trajectory(_line(250, 1.0), _pred09(), "none")
    assert res["sequences"]["09"]["t_err_pct"] == pytest.approx(direct["t_err_pct"], rel=1e-6)
    assert (tmp_path / "plots" / "09_trajectory.png").stat().st_size > 1000
    assert (tmp_path / "plots" / "09_segment_errors.png").stat().st_size > 1000


def _pred09() -> np.ndarray:
    pred = _line(250, 1.0)
    pred[:, :3, 3] *= 1.05
    pred[:, 1, 3] += np.linspace(0, 3, 250)
    return pred


def test_cli_writes_json_and_table(folders, tmp_path: Path) -> None:
    gt_dir, pred_dir = folders
    out = tmp_path / "m.json"
    proc = subprocess.run([sys.executable, "-m", "dfvo.evaluate", f"gt_dir={gt_dir}", f"pred_dir={pred_dir}",
                           "align=7dof", "seqs=[09,10]", f"out={out}"], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "alignment: 7dof" in proc.stdout and "average" in proc.stdout and " 09 " in proc.stdout
    data = json.loads(out.read_text())
    assert set(data["sequences"]) == {"09", "10"} and data["sequences"]["10"]["r_err_deg_per_100m"] is None
    for key in ("t_err_pct", "r_err_deg_per_100m", "ate_m", "rpe_m", "rpe_deg", "num_frames", "per_length"):
        assert key in data["sequences"]["09"]
    bad = subprocess.run([sys.executable, "-m", "dfvo.evaluate", f"gt_dir={gt_dir}", f"pred_dir={pred_dir}",
                          "seqs=[05]"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "05.txt" in bad.stderr


def test_plots_render_png(tmp_path: Path) -> None:
    gt = _line(300, 1.0)
    p = plot_trajectory(gt, gt * 1.1, tmp_path / "t.png", title="x")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 1000
    res = evaluate_trajectory(gt, gt, "7dof")
    q = plot_segment_errors(res["per_length"], tmp_path / "s.png")
    assert q.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and q.stat().st_size > 1000


@pytest.mark.parametrize("flag", ["--help", pytest.param("-h", marks=pytest.mark.slow)])  # Hydra's alias of --help
def test_cli_help_prints_usage_and_exits_0(flag: str) -> None:
    proc = subprocess.run([sys.executable, "-m", "dfvo.evaluate", flag], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: python -m dfvo.evaluate gt_dir=")
    for text in ("pred_dir=PATH", "align=MODE", "default: auto", "seqs=[A,B]", "exclude=[A]", "out=FILE",
                 "plot_dir=DIR", "example:"):
        assert text in proc.stdout, text


def test_integer_sequence_ids_get_two_digits(folders, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """seqs=[9,10] / exclude=[1] name 09.txt, 10.txt and 01, as infer.py seq=9 writes 09.txt (KittiOdometry)."""
    from dfvo.data.kitti_odometry import KittiOdometry
    from dfvo.evaluate import sequence_name

    args = parse_args(["gt_dir=a", "pred_dir=b", "seqs=[9, 10]", "exclude=[1]"])
    assert args["seqs"] == ["09", "10"] and args["exclude"] == ["01"]
    assert parse_args(["gt_dir=a", "pred_dir=b", "seqs=6"])["seqs"] == ["06"]
    assert [sequence_name(s) for s in (6, "6", "06", "123", "2011_09_26_drive_0001_sync")] == [
        "06", "06", "06", "123", "2011_09_26_drive_0001_sync"]
    for seq in ("6", "06", "123", "drive"):  # the same rule as the dataset that names infer.py's pose file
        with pytest.raises(FileNotFoundError, match=rf"sequences[/\\]{sequence_name(seq)}"):
            KittiOdometry(tmp_path / "none", seq)
    gt_dir, pred_dir = folders
    evaluate_in_process(f"gt_dir={gt_dir}", f"pred_dir={pred_dir}", "seqs=[9,10]", "align=none")
    table = capsys.readouterr().out
    assert " 09 " in table and " 10 " in table




def test_cli_single_files_write_nothing_else_in_the_working_directory(folders, tmp_path: Path, eval_cli) -> None:
    gt_dir, pred_dir = folders
    work = tmp_path / "work"
    work.mkdir()
    proc = eval_cli(f"gt={gt_dir / '09.txt'}", f"pred={pred_dir / '09.txt'}", "align=none", "out=m.json", cwd=work)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in work.iterdir()) == ["m.json"]  # no outputs/, .hydra/ or *.log
    data = json.loads((work / "m.json").read_text())
    assert data["task"] == "odometry" and list(data["sequences"]) == ["09"]
    direct = evaluate_trajectory(_line(250, 1.0), _pred09(), "none")
    assert data["sequences"]["09"]["t_err_pct"] == pytest.approx(direct["t_err_pct"], rel=1e-6)
    assert data["sequences"]["09"]["association"]["method"] == "order"
    bad = eval_cli(f"gt={gt_dir / '09.txt'}", f"pred={pred_dir / '09.txt'}", "bogus=1", cwd=work)
    assert bad.returncode != 0 and "bogus" in bad.stderr
    both = eval_cli(f"gt={gt_dir / '09.txt'}", f"gt_dir={gt_dir}", f"pred_dir={pred_dir}", cwd=work)
    assert both.returncode == 2 and both.stderr.startswith("error: both gt=") and len(both.stderr.splitlines()) == 1
    assert sorted(p.name for p in work.iterdir()) == ["m.json"]


def test_cli_prefix_and_timestamped_formats(tmp_path: Path, capsys: pytest.CaptureFixture, eval_cli) -> None:
    """A shorter KITTI prediction needs allow_prefix=true and the table says so; a TUM prediction is matched by
    timestamp against a EuRoC ground truth given as its dataset folder (<seq>/mav0/...)."""
    from dfvo.io.trajectory import write_euroc_poses, write_tum_poses

    gt, pred = _line(250, 1.0), _pred09()
    write_kitti_poses(tmp_path / "gt" / "09.txt", gt)
    write_kitti_poses(tmp_path / "pred" / "09.txt", pred[:120])
    refused = eval_cli(f"gt_dir={tmp_path / 'gt'}", f"pred_dir={tmp_path / 'pred'}")
    assert refused.returncode == 2 and "allow_prefix=true" in refused.stderr
    evaluate_in_process(f"gt_dir={tmp_path / 'gt'}", f"pred_dir={tmp_path / 'pred'}", "allow_prefix=true",
                        "align=none")
    table = capsys.readouterr().out
    assert "09: prefix: the first 120 of 250 ground-truth poses (allow_prefix=true)" in table
    assert " 120 " in table  # frames column: the evaluated poses

    stamps = 1403636579.0 + np.arange(250) * 0.05
    write_euroc_poses(tmp_path / "euroc" / "MH_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv", gt, stamps)
    write_tum_poses(tmp_path / "tum" / "MH_01.txt", pred[::2], stamps[::2] + 0.004)
    out = tmp_path / "e.json"
    evaluate_in_process(f"gt_dir={tmp_path / 'euroc'}", f"pred_dir={tmp_path / 'tum'}", "align=7dof", f"out={out}")
    table = capsys.readouterr().out
    assert "MH_01: 125 of 125 predicted poses matched by timestamp within 0.01 s (250 ground-truth poses" in table
    res = json.loads(out.read_text())["sequences"]["MH_01"]
    assert res["gt_format"] == "euroc" and res["pred_format"] == "tum"
    direct = evaluate_trajectory(gt[::2], pred[::2], "7dof")
    assert res["ate_m"] == pytest.approx(direct["ate_m"], rel=1e-6, abs=1e-9)
    assert res["rpe_m"] == pytest.approx(direct["rpe_m"], rel=1e-6)


def test_task_dispatch_writes_out(monkeypatch, tmp_path: Path) -> None:
    """task=flow|depth call dfvo.source_eval.flow.evaluate_flow_task / dfvo.source_eval.depth.evaluate_depth_task
    with the composed config (shared gt_dir/pred_dir) and the command writes their dict to out=."""
    from hydra import compose, initialize_config_module

    import dfvo.cli.evaluate as cli

    seen = {}

    def fake_task(task: str):
        def evaluate(cfg):
            seen[task] = cfg
            return {"task": task, "value": 1.5}
        return evaluate

    for task in ("flow", "depth"):
        monkeypatch.setattr(cli, f"evaluate_{task}_task", fake_task(task))
        monkeypatch.setattr(cli, f"format_{task}_table", lambda result: f"table of {result['task']}")
    with initialize_config_module(config_module="dfvo.conf.evaluate", version_base="1.3"):
        for task in ("flow", "depth"):
            out = tmp_path / f"{task}.json"
            cfg = compose(config_name="evaluate", overrides=[f"task={task}", "gt_dir=G", "pred_dir=P", f"out={out}"])
            assert cli.run(cfg) == {"task": task, "value": 1.5}
            assert seen[task].gt_dir == "G" and seen[task].pred_dir == "P"
            assert json.loads(out.read_text()) == {"task": task, "value": 1.5}
        with pytest.raises(ValueError, match=r"task='pose'; expected one of \['odometry', 'flow', 'depth'\]"):
            cli.run(compose(config_name="evaluate", overrides=["task=pose"]))


def test_task_settings_that_do_not_compose_are_one_line(eval_cli) -> None:
    """The typed flow/depth settings are checked when Hydra composes: a bad value or an unknown key ends, like other
    bad input, with one ``error:`` line naming the key and exit status 2."""
    bad = eval_cli("task=flow", "gt_dir=G", "flow.layout=kitti2020", "depth.network.bogus=1")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert bad.stderr.startswith("error: ") and "flow.layout=kitti2020" in bad.stderr
    assert "expected one of [kitti2015, kitti2012]" in bad.stderr


def test_multirun_folder_is_per_user(folders, tmp_path: Path) -> None:
    """Issue 42: ``-m`` writes Hydra's sweep files under ``$TMPDIR/dfvo-eval-multirun-uUID``; another user's
    ``dfvo-eval-multirun`` (not writable, here a file in the way) does not matter."""
    gt_dir, pred_dir = folders
    (tmp_path / "dfvo-eval-multirun").write_text("another user's")
    proc = subprocess.run([sys.executable, "-m", "dfvo.evaluate", "-m", f"gt_dir={gt_dir}", f"pred_dir={pred_dir}",
                           "align=7dof,6dof", "seqs=[09]"], cwd=REPO, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, TMPDIR=str(tmp_path)))
    assert proc.returncode == 0, proc.stderr[-2000:]
    sweeps = list((tmp_path / f"dfvo-eval-multirun-u{os.getuid()}").glob("*/multirun.yaml"))
    assert len(sweeps) == 1 and proc.stdout.count("alignment:") == 2


def test_align_auto_reads_as_the_run_reported_it(folders, tmp_path: Path) -> None:
    """Issue 42: an infer.py run (6-DoF in its metrics.json) evaluated again with the default align=auto gives the
    run's own 6-DoF numbers and says so (the default was 7-DoF: 0.0108 against the run's 0.0112 m); predictions
    without an infer.py metrics.json get 7-DoF."""
    gt_dir, pred_dir = folders
    assert parse_args(["gt_dir=a", f"pred_dir={pred_dir}"])["align"] == "7dof"
    (pred_dir / "metrics.json").write_text(json.dumps({"sequence": "09", "align": "6dof"}))
    assert parse_args(["gt_dir=a", f"pred_dir={pred_dir}"])["align"] == "6dof"
    assert parse_args(["gt_dir=a", f"pred={pred_dir / '09.txt'}"])["align"] == "6dof"
    assert parse_args(["gt_dir=a", f"pred_dir={pred_dir}", "align=7dof"])["align"] == "7dof"
    out = tmp_path / "m.json"
    proc = subprocess.run([sys.executable, "-m", "dfvo.evaluate", f"gt={gt_dir / '09.txt'}",
                           f"pred={pred_dir / '09.txt'}", f"out={out}"], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    note = f"align=auto: 6dof, the alignment infer.py reported this run with ({pred_dir / 'metrics.json'})"
    assert note in proc.stdout
    direct = evaluate_trajectory(_line(250, 1.0), _pred09(), "6dof")
    got = json.loads(out.read_text())["sequences"]
    assert next(iter(got.values()))["rpe_m"] == pytest.approx(direct["rpe_m"], rel=1e-9)
