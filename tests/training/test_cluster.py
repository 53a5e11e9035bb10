"""Beyond one machine: the Slurm launcher config (hydra-submitit-launcher, the optional extra ``cluster``) composes
against the plugin's schema, the same plugin runs a 2-job infer sweep as local processes (``submitit_local``), and
``trainer=ddp`` trains with 2 CPU processes (gloo) and resumes from its checkpoint."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

REPO = Path(__file__).resolve().parents[2]
pytest.importorskip("hydra_plugins.hydra_submitit_launcher",
                    reason='needs the cluster extra: pip install "dfvo[cluster]"')


def _env() -> dict[str, str]:
    return dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")


def test_slurm_launcher_config_is_the_plugins(tmp_path: Path) -> None:
    """hydra/launcher=slurm composes into the plugin's SlurmLauncher with our resources, and a value of the wrong type
    fails at compose time (the file extends the plugin's schema-checked config)."""
    from hydra.utils import instantiate

    import dfvo.inference.config  # noqa: F401  (stores the schemas the infer configs extend)

    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
        cfg = compose("infer", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=gpu"],
                      return_hydra_config=True)
        launcher = cfg.hydra.launcher
        assert launcher.partition == "gpu" and launcher.cpus_per_task == 4 and launcher.timeout_min == 120
        made = instantiate(launcher)  # (Hydra's plugin discovery may load the module twice: compare by name)
        assert type(made).__qualname__ == "SlurmLauncher" and made.params["partition"] == "gpu"
        with pytest.raises(Exception, match="cpus_per_task"):  # typed by the plugin's schema
            compose("infer", overrides=["hydra/launcher=slurm", "hydra.launcher.cpus_per_task=four"],
                    return_hydra_config=True)


def test_ddp_trainer_config_builds_two_cpu_processes(tmp_path: Path) -> None:
    """trainer=ddp trainer.devices=2 trainer.accelerator=cpu: a DDP strategy over 2 CPU processes (gloo)."""
    from lightning.pytorch.strategies import DDPStrategy

    from dfvo.training.config import register_configs
    from dfvo.training.runner import build_trainer

    register_configs()

    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "train"), version_base="1.3"):
        cfg = compose("train", overrides=["trainer=ddp", "trainer.devices=2", "trainer.accelerator=cpu",
                                          f"runs_dir={tmp_path}", "trainer.logger=false"])
    trainer = build_trainer(cfg, tmp_path / "run")
    assert isinstance(trainer.strategy, DDPStrategy)
    assert trainer.num_devices == 2 and trainer.world_size == 2 and trainer.num_nodes == 1
    assert trainer.strategy.root_device == torch.device("cpu")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_submitit_local_two_job_sweep(tmp_path: Path) -> None:
    """A 2-job infer sweep through the submitit plugin (local processes): both jobs write their outputs, each in its
    own job folder, and submitit keeps its logs under the sweep folder."""
    out = tmp_path / "sweep"
    args = ["-m", "hydra/launcher=submitit_local", "tracker=hybrid,pnp", "flow=oracle", "depth=oracle",
            "data.num_frames=4", "img_res.height=64", "img_res.width=224", "progress=false", "num_threads=1",
            f"out_dir={out}"]
    proc = subprocess.run([sys.executable, "infer.py", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=840, env=_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = sorted(p for p in out.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name.rsplit("tracker=", 1)[1] for p in jobs] == ["hybrid", "pnp"]
    for job in jobs:
        summary = json.loads((job / "summary.json").read_text())
        assert summary["frames_written"] == 4 and not summary["partial"]
        assert len((job / "synthetic_drive_s0.txt").read_text().splitlines()) == 4
    assert list((out / ".submitit").rglob("*_log.out"))  # submitit ran the jobs


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_ddp_two_cpu_processes_train_and_resume(tmp_path: Path) -> None:
    """trainer=ddp with 2 gloo processes trains 2 steps, then resumes from last.ckpt to step 4."""
    common = ["trainer=ddp", "trainer.devices=2", "trainer.accelerator=cpu", "model=depth_mono_sc", "data=synthetic",
              "data.height=64", "data.width=128", "data.batch_size=1", "data.val_num_frames=3", "data.num_frames=5",
              "data.seeds=[0]", "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1", "threads=1",
              f"runs_dir={tmp_path}", "name=ddp"]

    def train(*extra: str) -> subprocess.CompletedProcess:
        proc = subprocess.run([sys.executable, str(REPO / "train.py"), *common, *extra], cwd=tmp_path,
                              capture_output=True, text=True, timeout=700, env=_env())
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "MEMBER: 2/2" in proc.stderr and "distributed_backend=gloo" in proc.stderr  # two ranks joined
        return proc

    train("trainer.max_steps=2")
    last = tmp_path / "ddp" / "checkpoints" / "last.ckpt"
    first = torch.load(last, map_location="cpu", weights_only=False)
    assert first["global_step"] == 2
    proc = train("trainer.max_steps=4", f"ckpt_path={last}")
    assert "done: step 4" in proc.stdout and "Restoring states from the checkpoint" in proc.stderr
    second = torch.load(last, map_location="cpu", weights_only=False)
    assert second["global_step"] == 4
    changed = [k for k, v in first["state_dict"].items()
               if v.is_floating_point() and not torch.equal(v, second["state_dict"][k])]
    assert changed  # the resumed run trained further
