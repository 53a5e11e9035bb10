"""A training run stopped by SIGTERM (a cluster's time limit) or SIGINT (Ctrl-C) mid-epoch writes last.ckpt for the
step it finished, says so in one line and exits 143 / 130; resuming from that checkpoint ends with the weights of
an uninterrupted run (issue 28). A run killed by SIGKILL (or a power loss) mid-epoch keeps its last periodic
checkpoint, and ``resume=auto`` continues it from there to the same weights (issue 37)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]
# 40 steps of a tiny step-scheduled flow run (one synthetic world, FlowNet "tiny" at 32x96), one line per step
RUN = ["model=flow_mix", "data=flow_mix", "model.variant=tiny", "data.height=32", "data.width=96", "data.seeds=[0]",
       "data.num_frames=6", "data.frame_skips=[1]", "data.max_flow=null", "data.val_seeds=[]", "data.batch_size=2",
       "model.phases=[{name: sup, steps: 40, lr: 1.0e-4}]", "model.log_images_every=0", "threads=1",
       "trainer.logger=false", "trainer.enable_progress_bar=false", "trainer.print_every_n_steps=1",
       "trainer.checkpoint_every_n_steps=1000"]


def _cmd(tmp_path: Path, name: str, *extra: str) -> list[str]:
    return [sys.executable, "train.py", *RUN, f"runs_dir={tmp_path}", f"data.cache_dir={tmp_path / 'cache'}",
            f"name={name}", *extra]


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location="cpu", weights_only=False)["state_dict"]


ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> dict[str, torch.Tensor]:
    """The final weights of the run without a signal."""
    tmp_path = tmp_path_factory.mktemp("whole")
    whole = subprocess.run(_cmd(tmp_path, "whole"), cwd=REPO, capture_output=True, text=True, env=ENV, timeout=600)
    assert whole.returncode == 0, whole.stderr[-3000:]
    return _weights(tmp_path / "whole" / "checkpoints" / "last.ckpt")


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 143),
                                           pytest.param(signal.SIGINT, 130, marks=pytest.mark.slow)])
def test_signal_mid_epoch_saves_and_resumes_exactly(tmp_path: Path, sig: signal.Signals, code: int,
                                                     uninterrupted: dict[str, torch.Tensor]) -> None:
    """SIGTERM (SIGINT, slow: the same path) after step 5 of 40: exit 143 (130), one line naming the checkpoint of
    the last finished step; resuming from it ends with the uninterrupted run's weights, bitwise."""
    env = ENV
    proc = subprocess.Popen(_cmd(tmp_path, "stopped"), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env)
    lines = []
    deadline = time.monotonic() + 300
    assert proc.stdout is not None
    for line in proc.stdout:  # wait until training is under way (step 5 logged)
        lines.append(line)
        if " step 5/" in line or time.monotonic() > deadline:
            break
    proc.send_signal(sig)
    rest, _ = proc.communicate(timeout=300)
    output = "".join(lines) + rest
    assert proc.returncode == code, output[-3000:]
    ckpt = tmp_path / "stopped" / "checkpoints" / "last.ckpt"
    step = torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"]
    assert 5 <= step < 40, step
    message = [line for line in output.splitlines() if line.startswith("dfvo-train:")]
    assert len(message) == 1 and f"stopped by {sig.name} at step {step}; saved {ckpt}" in message[0], output[-2000:]
    assert "Traceback" not in output
    assert (tmp_path / "stopped" / "weights.safetensors").is_file()

    resumed = subprocess.run(_cmd(tmp_path, "stopped", f"ckpt_path={ckpt}"), cwd=REPO, capture_output=True,
                             text=True, env=env, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a, b = _weights(tmp_path / "stopped" / "checkpoints" / "last.ckpt"), uninterrupted
    assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def test_signal_before_training_stops_at_once(tmp_path: Path) -> None:
    """A SIGTERM while the data is still being prepared (a world of 40 frames rendering) ends at once with exit 143
    and one line; nothing is trained or saved."""
    cmd = _cmd(tmp_path, "early", "data.num_frames=40", "data.height=96", "data.width=320",
               "data.frame_skips=[1,2,3]")
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.stdout is not None
    for line in proc.stdout:
        if "flow_mix" in line or "data=" in line or "Seed" in line or "training" in line:
            break
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 143, out[-2000:]
    assert "stopped by SIGTERM before training started; nothing to save" in out
    assert not (tmp_path / "early" / "checkpoints" / "last.ckpt").exists()


def test_sigkill_mid_epoch_then_resume_auto(tmp_path: Path, uninterrupted: dict[str, torch.Tensor]) -> None:
    """SIGKILL after step 12 of 40, checkpoints every 5 steps: last.ckpt holds step 10 (whole: written to a temporary
    file and renamed), previous.ckpt step 5; `resume=auto` says it resumes from step 10 and ends with the
    uninterrupted run's weights, bitwise (so the optimiser state and data position were restored too)."""
    cmd = _cmd(tmp_path, "killed", "resume=auto", "trainer.checkpoint_every_n_steps=5")
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    deadline = time.monotonic() + 300
    assert proc.stdout is not None
    output = []
    for line in proc.stdout:
        output.append(line)
        if " step 12/" in line or time.monotonic() > deadline:
            break
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL, "".join(output)[-2000:]
    folder = tmp_path / "killed" / "checkpoints"
    last = torch.load(folder / "last.ckpt", map_location="cpu", weights_only=False)
    assert last["global_step"] == 10 and not (tmp_path / "killed" / "finished.json").exists()
    assert torch.load(folder / "previous.ckpt", map_location="cpu", weights_only=False)["global_step"] == 5

    resumed = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=ENV, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    log = resumed.stdout + resumed.stderr
    assert f"resume=auto: resuming {tmp_path / 'killed'} from {folder / 'last.ckpt'} (step 10," in log, log[-3000:]
    assert "training from step 10 of 40" in log
    a, b = _weights(folder / "last.ckpt"), uninterrupted
    assert set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)
    assert (tmp_path / "killed" / "finished.json").is_file()
