"""The experiment files (dfvo/conf/train/experiment/): each holds only its differences from the defaults, and each
shipped network's stages train a few steps with `trainer=smoke` at a tiny size, so the model card's commands cannot
rot (issue 25)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from dfvo.io.checkpoint import find_checkpoint
from dfvo.training.config import data_config, model_config
from dfvo.training.runner import run_training

REPO = Path(__file__).resolve().parents[2]
EXPERIMENTS = REPO / "dfvo" / "conf" / "train" / "experiment"
NAMES = sorted(p.stem for p in EXPERIMENTS.glob("*.yaml"))
# flow experiments at a tiny size: 1 world of 6 frames, network 32x96, FlowNet "tiny", one held-out scenario
TINY_FLOW = ["model.variant=tiny", "data.height=32", "data.width=96", "data.num_frames=6", "data.max_train_samples=4",
             "data.val_scenarios=[drive]", "data.val_seeds=[1002]", "data.val_num_frames=3", "data.kitti_batch_size=1",
             "data.drives=[2011_09_26_drive_0001]", "data.device=cpu", "data.batch_size=2"]
TINY_DEPTH = ["data.height=64", "data.width=128", "data.batch_size=1", "data.val_num_frames=3",
              "data.max_train_samples=4"]


def _compose(*overrides: str):
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        return compose("train", overrides=list(overrides))


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


@pytest.mark.parametrize("name", NAMES)
def test_experiment_holds_only_its_differences(name: str) -> None:
    """`# @package _global_`, group choices by `override /GROUP: X`, and every value it sets differs from the config
    composed with those group choices alone."""
    text = (EXPERIMENTS / f"{name}.yaml").read_text()
    assert text.startswith("# @package _global_"), name
    raw = yaml.safe_load(text)
    groups = [entry.removeprefix("override /").replace(": ", "=") for d in raw.get("defaults", [])
              for entry in [next(f"{k}: {v}" for k, v in d.items())]]
    assert all(g.split("=")[0] in ("model", "data", "trainer") for g in groups), groups
    base = OmegaConf.to_container(_compose(*groups), enum_to_str=True)
    for key, value in _flat({k: v for k, v in raw.items() if k != "defaults"}).items():
        assert OmegaConf.select(OmegaConf.create(base), key) != value, f"{name}.yaml repeats {key}={value}"
    assert not [v for v in _flat(raw).values() if "shared" in str(v)], f"{name}.yaml assumes the repo layout"
    cfg = _compose(f"experiment={name}")
    model_config(cfg), data_config(cfg)  # the typed schemas accept it
    assert cfg.name == name


def test_flow_fast_is_the_recorded_recipe() -> None:
    """flow_fast restates flow_v3 (model card): init the flow_stage2 run's weights, 24 worlds of seeds 0-23 cycling
    drive, city, straight, highway, 0.3-3 m/frame, skips 1-3, max flow 160 px, 96x320 at 640x192, sup 4500 + mix
    1500, batch 4 + 2 KITTI pairs, clipping 10, lr 1e-4 / 2e-5 /10 for the last quarter of each phase."""
    cfg = _compose("experiment=flow_fast")
    m, d = model_config(cfg), data_config(cfg)
    assert m.init_from == str(Path(cfg.runs_dir).expanduser() / "flow_stage2" / "weights.safetensors")
    assert m.variant == "small" and m.grad_clip_norm == 10
    assert [(p.steps, p.lr, p.synthetic, p.kitti) for p in m.phases] == [(4500, 1e-4, True, False),
                                                                        (1500, 2e-5, True, True)]
    assert m.lr_drop_fraction == 0.75 and m.self_weight == 1.0
    assert (m.augment.flip_prob, m.augment.gray_prob, m.augment.jitter) == (0.5, 0.3, True)
    assert d.seeds == list(range(24)) and d.scenario == ["drive", "city", "straight", "highway"]
    assert (d.speed, d.frame_skips, d.max_flow, d.num_frames) == ([0.3, 3.0], [1, 2, 3], 160.0, 40)
    assert (d.height, d.width, d.render_scale, d.batch_size, d.kitti_batch_size) == (96, 320, 2, 4, 2)


def _run(tmp_path: Path, *overrides: str) -> dict:
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        cfg = compose("train", overrides=[f"runs_dir={tmp_path}", "trainer=smoke", "threads=1",
                                          "trainer.logger=false", *overrides])
    return run_training(cfg)


def test_flow_fast_smoke(tmp_path: Path, kitti_raw_root: Path) -> None:
    """`python train.py experiment=flow_fast trainer=smoke` (tiny): 3 steps, the held-out metric, last.ckpt only."""
    out = _run(tmp_path, "experiment=flow_fast", f"data.root={kitti_raw_root.parent}", *TINY_FLOW,
               "model.init_from=null")
    assert out["global_step"] == 3 and "val/epe" in out["metrics"]
    assert sorted(p.name for p in (tmp_path / "flow_fast" / "checkpoints").iterdir()) == ["last.ckpt"]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "first_phase_steps"),
                         [("flow_allspeed", 1), ("flow_gpu", 1), ("flow_tiny", 1), ("flow_every_distill", None)])
def test_other_flow_experiments_smoke(tmp_path: Path, kitti_raw_root: Path, name: str,
                                      first_phase_steps: int | None) -> None:
    """The other step-scheduled flow experiments, with the phases shortened so the mixed phase runs too (flow_tiny
    and flow_every_distill, whose one phase is the mixed one: with the shipped flow.safetensors teaching their KITTI
    pairs)."""
    shorten = [f"model.phases.0.steps={first_phase_steps}"] if first_phase_steps else []
    out = _run(tmp_path, f"experiment={name}", f"data.root={kitti_raw_root.parent}", *TINY_FLOW,
               "model.init_from=null", *shorten)
    assert out["global_step"] == 3 and "train/self_loss" in out["metrics"]
    assert ("train/distill_epe" in out["metrics"]) == (name in ("flow_tiny", "flow_every_distill"))


@pytest.mark.slow
def test_flow_stages_chain(tmp_path: Path, kitti_raw_root: Path) -> None:
    """flow.safetensors's two stages: stage 2 starts from stage 1's last.ckpt and ends self-supervised."""
    one = _run(tmp_path, "experiment=flow_stage1", *TINY_FLOW)
    assert one["global_step"] == 3
    two = _run(tmp_path, "experiment=flow_stage2", f"data.root={kitti_raw_root.parent}", *TINY_FLOW,
               "model.phases.0.steps=2")
    m = two["metrics"]
    assert two["global_step"] == 3 and m["train/phase"] == 1.0  # the last step is in the self-supervised phase
    assert m["train/loss"] == pytest.approx(m["train/self_loss"])  # ... whose loss is the self-supervised one alone
    assert two["module"].hparams["cfg"]["model"]["initialised_from"] == str(tmp_path / "flow_stage1" / "checkpoints"
                                                                            / "last.ckpt")


@pytest.mark.slow
def test_depth_stages_chain(tmp_path: Path, kitti_raw_root: Path) -> None:
    """depth.safetensors's two stages: stage 2 starts from stage 1's weights.safetensors."""
    one = _run(tmp_path, "experiment=depth_stage1", f"data.root={kitti_raw_root.parent}", *TINY_DEPTH,
               "data.num_frames=4")
    assert one["global_step"] == 3 and (tmp_path / "depth_stage1" / "weights.safetensors").is_file()
    two = _run(tmp_path, "experiment=depth_stage2", f"data.root={kitti_raw_root.parent}", *TINY_DEPTH)
    assert two["global_step"] == 3
    assert two["module"].hparams["cfg"]["model"]["initialised_from"] == str(tmp_path / "depth_stage1"
                                                                            / "weights.safetensors")


def test_train_py_experiment_smoke_cli(tmp_path: Path, kitti_raw_root: Path) -> None:
    """The command line form of the model card, as a user runs it (fresh process; from the shipped flow.safetensors):
    exit 0, `done:` printed, no Lightning line twice, no advert, no warning, and only last.ckpt kept."""
    tiny = [o for o in TINY_FLOW if not o.startswith("model.variant")]  # the shipped small network it starts from
    cmd = [sys.executable, "train.py", "experiment=flow_fast", "trainer=smoke", f"runs_dir={tmp_path}", "threads=1",
           f"data.root={kitti_raw_root.parent}", "model.init_from=checkpoints/flow.safetensors", *tiny]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    lines = [line for line in (res.stdout + res.stderr).splitlines() if line.strip()]
    assert "done: step 3" in res.stdout
    body = [line.split("]", 1)[-1] for line in lines]  # without the time stamps
    assert len(body) == len(set(body)), "\n".join(lines)
    noise = ("litlogger", "litmodels", "Tip:", "Warning", "deprecated")
    assert not [line for line in lines if any(n in line for n in noise)], lines
    assert sorted(p.name for p in (tmp_path / "flow_fast" / "checkpoints").iterdir()) == ["last.ckpt"]


def test_depth_hints_smoke(tmp_path: Path, kitti_raw_root: Path) -> None:
    """`python train.py experiment=depth_hints trainer=smoke` (tiny): the SGBM hints are computed into the frame
    cache, used by the loss (its terms logged), from the shipped depth network (a package path)."""
    out = _run(tmp_path, "experiment=depth_hints", f"data.root={kitti_raw_root.parent}", *TINY_DEPTH)
    assert out["global_step"] == 3 and "train/depth_hints_s0" in out["metrics"]
    assert list((tmp_path / "frame_cache").glob("*_sgbm_hints_64x128_*.npy"))
    assert out["module"].hparams["cfg"]["model"]["initialised_from"].endswith("checkpoints/depth.safetensors")


def test_depth_small_smoke(tmp_path: Path, kitti_raw_root: Path) -> None:
    """`python train.py experiment=depth_small trainer=smoke` (tiny): the half-width network distils from the network
    at RUNS/depth_scene_shadow/weights.safetensors (here a saved full-width one), the distillation terms are logged,
    and the export records its width."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    from dfvo.models.depth_net import DepthNet

    teacher = tmp_path / "depth_scene_shadow" / "weights.safetensors"
    teacher.parent.mkdir()
    save_file({k: v.contiguous() for k, v in DepthNet(init_depth=10.0).state_dict().items()}, str(teacher),
              metadata={"task": "depth", "width_multiplier": "1.0"})
    out = _run(tmp_path, "experiment=depth_small", f"data.root={kitti_raw_root.parent}", *TINY_DEPTH)
    assert out["global_step"] == 3 and "train/distill_s0" in out["metrics"]
    assert out["module"].depth_net.encoder.num_ch_enc == (32, 32, 64, 128, 256)
    with safe_open(str(tmp_path / "depth_small" / "weights.safetensors"), "pt") as f:
        assert f.metadata()["width_multiplier"] == "0.5"


def test_campaign_followups_read_their_predecessors_in_the_runs_folder(tmp_path: Path) -> None:
    """depth_scene_shadow starts from depth_scene's export, depth_small distils from depth_scene_shadow's and
    depth_paste starts from it, all in the runs folder the campaign passes (``runs_dir``, ``~`` expanded), where a
    new machine's queue restores a finished run's export (tests/training/test_campaign.py)."""
    shadow = model_config(_compose("experiment=depth_scene_shadow", f"runs_dir={tmp_path}"))
    assert shadow.init_from == str(tmp_path / "depth_scene" / "weights.safetensors")
    assert shadow.augment.shadow_prob == 0.5
    paste = model_config(_compose("experiment=depth_paste", f"runs_dir={tmp_path}"))
    assert paste.init_from == str(tmp_path / "depth_scene_shadow" / "weights.safetensors")
    assert paste.augment.paste_prob == 0.5 and not paste.temporal and paste.w_depth_supervised > 0
    taught = model_config(_compose("experiment=depth_paste_teacher", f"runs_dir={tmp_path}"))
    assert taught.teacher == taught.init_from == paste.init_from and taught.w_distill == 1.0
    assert taught.augment == paste.augment and not taught.temporal  # depth_paste's objects, with the teacher
    hinted = model_config(_compose("experiment=depth_paste_hints", f"runs_dir={tmp_path}"))
    filled = model_config(_compose("experiment=depth_paste_hints_fill", f"runs_dir={tmp_path}"))
    assert hinted.w_depth_hints > 0 and not hinted.distill_where_no_target
    assert filled.distill_where_no_target and filled.teacher == taught.teacher and filled.w_distill == 1.0
    assert filled.augment == hinted.augment == paste.augment and filled.w_depth_hints == hinted.w_depth_hints
    rows = model_config(_compose("experiment=depth_paste_hints_rows", f"runs_dir={tmp_path}"))
    assert rows.depth_hints_from_row == 0.667 and rows.distill_where_no_target and rows.teacher == filled.teacher
    shipped = model_config(_compose("experiment=depth_rows_shipped_teacher", f"runs_dir={tmp_path}"))
    assert find_checkpoint(shipped.teacher) == REPO / "dfvo" / "checkpoints" / "depth.safetensors"
    assert replace(shipped, teacher=rows.teacher) == rows  # the rows run but for the teacher
    scaled = model_config(_compose("experiment=depth_rows_scaled_teacher", f"runs_dir={tmp_path}"))
    assert replace(scaled, distill_scale_from_hints=False) == shipped and scaled.distill_scale_from_hints
    small = model_config(_compose("experiment=depth_small", "runs_dir='~/some-runs'"))
    assert small.teacher == str(Path.home() / "some-runs" / "depth_scene_shadow" / "weights.safetensors")
    assert small.width_multiplier == 0.5 and small.w_distill > 0
    distill = model_config(_compose("experiment=flow_every_distill", f"runs_dir={tmp_path}"))
    assert distill.init_from == str(tmp_path / "flow_every" / "weights.safetensors")
    assert distill.teacher and distill.w_distill > 0 and all(p.kitti for p in distill.phases)
