"""scripts/campaign.sh: the queue runs each run with resume=auto into the runs folder, skips finished runs, stops at
a failed one, and reports progress (issue 37)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "campaign.sh"
TINY = ("model=flow_mix data=flow_mix model.variant=tiny data.height=32 data.width=96 data.seeds=[0] "
        "data.num_frames=5 data.frame_skips=[1] data.max_flow=null data.val_seeds=[] data.batch_size=2 "
        "model.log_images_every=0 trainer.logger=false trainer.precision=32-true "
        "model.phases=[{name:sup,steps:30,lr:1.0e-4}]")

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def _campaign(runs: Path, queue: Path, *args: str, extra_env: dict[str, str] | None = None
              ) -> subprocess.CompletedProcess:
    env = {**os.environ, "DFVO_RUNS_DIR": str(runs), "CAMPAIGN_QUEUE": str(queue), "CAMPAIGN_CODE": str(REPO),
           "OMP_NUM_THREADS": "1", **(extra_env or {})}
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, env=env, timeout=600)


def test_queue_runs_resumes_skips_and_stops_at_a_failure(tmp_path: Path) -> None:
    runs, queue = tmp_path / "runs", tmp_path / "queue"
    queue.write_text(f"# a comment\n\nfirst  {TINY}\nbroken {TINY} model.no_such_key=1\nthird  {TINY}\n")
    res = _campaign(runs, queue, "run")
    assert res.returncode == 0, res.stderr
    log = (runs / "campaign.log").read_text()
    assert (runs / "first" / "finished.json").is_file()
    assert "first: finished" in log and "step 25/30" in log and "steps/h ETA" in log
    assert "resume=auto: " in log  # train.py ran with resume=auto
    assert "broken: failed" in log and "the queue stops here" in log
    assert not (runs / "third").exists() and not (runs / "campaign.pid").exists()

    queue.write_text(f"first  {TINY}\nthird  {TINY} trainer.max_steps=10\n")
    res = _campaign(runs, queue, "run")
    log = (runs / "campaign.log").read_text()
    assert "first: finished ({" in log and "; next" in log  # skipped: finished.json
    assert (runs / "third" / "finished.json").is_file()
    status = _campaign(runs, queue, "status").stdout
    assert "campaign: not running" in status and "first: finished" in status and "third: finished" in status


def test_start_refuses_a_python_without_the_project(tmp_path: Path) -> None:
    """A PYTHON that cannot import the project's packages is refused by `start` in one line naming it, before anything
    runs in the background (a queue that failed there would be found only in the log)."""
    runs, queue = tmp_path / "runs", tmp_path / "queue"
    queue.write_text(f"first  {TINY}\n")
    env = {**os.environ, "DFVO_RUNS_DIR": str(runs), "CAMPAIGN_QUEUE": str(queue), "CAMPAIGN_CODE": str(REPO),
           "PYTHON": "/bin/false"}
    res = subprocess.run(["bash", str(REPO / "scripts" / "campaign.sh"), "start"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2 and "PYTHON=/bin/false cannot import" in res.stderr
    assert not (runs / "campaign.pid").exists() and not (runs / "first").exists()


def test_snapshot_and_restore_carry_the_queue_to_a_new_machine(tmp_path: Path) -> None:
    """`snapshot` commits a finished run's network and finished.json and an unfinished run's small last.ckpt; on a new
    machine (an empty runs folder) the queue skips the finished run, whose network the runs after it find in its
    folder, and resumes the unfinished one from its checkpoint."""
    runs, queue, snap = tmp_path / "runs", tmp_path / "queue", tmp_path / "campaign"
    env = {"CAMPAIGN_SNAPSHOT": str(snap)}
    queue.write_text(f"first  {TINY} trainer.max_steps=10\nsecond {TINY}\n")
    (runs / "second" / "checkpoints").mkdir(parents=True)
    (runs / "second" / "checkpoints" / "last.ckpt").write_bytes(b"not a real checkpoint")
    queue_first = tmp_path / "queue_first"
    queue_first.write_text(f"first  {TINY} trainer.max_steps=10\n")
    assert _campaign(runs, queue_first, "run").returncode == 0
    res = _campaign(runs, queue, "snapshot", extra_env=env)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (snap / "first").iterdir()) == ["finished.json", "weights.safetensors"]
    weights = (runs / "first" / "weights.safetensors").read_bytes()
    assert (snap / "first" / "weights.safetensors").read_bytes() == weights
    assert (snap / "second" / "last.ckpt").read_bytes() == b"not a real checkpoint"
    assert "first: finished: weights.safetensors and finished.json" in res.stdout
    assert "first" not in _campaign(runs, queue, "snapshot", extra_env=env).stdout  # unchanged: nothing copied

    new = tmp_path / "new_machine"
    res = _campaign(new, queue_first, "run", extra_env=env)
    log = (new / "campaign.log").read_text()
    assert "first: restored the committed finished run" in log and "first: finished ({" in log and "; next" in log
    assert (new / "first" / "weights.safetensors").read_bytes() == weights
    assert "start or resume" not in log  # nothing trained again
    res = _campaign(new, queue, "run", extra_env=env)  # the unfinished run comes back from its committed checkpoint
    log = (new / "campaign.log").read_text()
    assert "second: restored the committed state" in log
    assert (new / "second" / "checkpoints" / "last.ckpt").read_bytes() == b"not a real checkpoint"


def test_a_depth_run_committed_as_weights_continues_on_a_new_machine(tmp_path: Path) -> None:
    """A depth run whose last.ckpt is too large to commit is snapshotted as its weights; on a new machine the queue
    copies them into the run folder and runs train.py with continue_from, which trains the epochs to go."""
    depth = ("model=depth_mono_sc data=synthetic data.num_frames=5 data.seeds=[0] data.height=64 data.width=128 "
             "data.batch_size=1 data.max_train_samples=2 data.val_num_frames=3 trainer.max_epochs=4 "
             "model.monitor=null model.log_images_every=0 trainer.logger=false trainer.precision=32-true")
    runs, queue, snap = tmp_path / "runs", tmp_path / "queue", tmp_path / "campaign"
    env = {"CAMPAIGN_SNAPSHOT": str(snap)}
    part = tmp_path / "part_queue"
    part.write_text(f"deep {depth} trainer.max_steps=3\n")
    assert _campaign(runs, part, "run").returncode == 0
    (runs / "deep" / "finished.json").unlink()  # as if stopped at step 3 (a SIGTERM leaves no finished.json)
    with open(runs / "deep" / "checkpoints" / "last.ckpt", "r+b") as f:
        f.truncate(60_000_000)  # a depth run's checkpoint: too large to commit (sparse: no disk used)
    queue.write_text(f"deep {depth}\n")
    res = _campaign(runs, queue, "snapshot", extra_env=env)
    assert "deep: weights.safetensors -> " in res.stdout and "(last.ckpt is 60 MB)" in res.stdout
    assert sorted(p.name for p in (snap / "deep").iterdir()) == ["weights.safetensors"]

    new = tmp_path / "new_machine"
    res = _campaign(new, queue, "run", extra_env=env)
    assert res.returncode == 0, res.stderr
    log = (new / "campaign.log").read_text()
    assert "deep: no checkpoint here: continues from the committed weights" in log
    assert f"continue_from={new / 'deep' / 'continue_from.safetensors'}" in log
    assert "the run continues after step 3 (epoch 1): 3 epochs to go" in log and "deep: finished" in log
    committed = (snap / "deep" / "weights.safetensors").read_bytes()
    assert (new / "deep" / "continue_from.safetensors").read_bytes() == committed
    assert '"step": 6' in (new / "deep" / "finished.json").read_text()  # epochs 1-3: 2 steps each
