"""Step-scheduled flow training (model=flow_mix data=flow_mix): one Lightning step equals the plain-PyTorch step of
the recipe on the same batch, the render cache, the schedule, the held-out validation, exact resume mid-run across a
phase boundary, and the one-line refusals of bad input (issue 25)."""

from __future__ import annotations

import re
from pathlib import Path

import lightning as L
import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from torch.utils.data import DataLoader

from dfvo.losses.flow_losses import multiscale_epe, self_supervised_flow_loss
from dfvo.matching.flow_warp import flow_magnitude
from dfvo.training.flow_data import FlowMixDataModule, FlowStepBatches, SyntheticPairs, phase_at
from dfvo.training.flow_module import FlowModule
from dfvo.training.flow_renders import (
    RENDER_FORMAT,
    RenderCacheError,
    WorldRender,
    cached_world,
    downsample_flow,
    render_world,
)
from dfvo.training.runner import run_training
from dfvo.training.sampling import step_generator

# a tiny recipe: 2 worlds of 6 frames, network 32x96 (working size 64x192), FlowNet "tiny"
TINY = ["model=flow_mix", "data=flow_mix", "model.variant=tiny", "data.height=32", "data.width=96",
        "data.seeds=[0,1]", "data.num_frames=6", "data.frame_skips=[1,2]", "data.max_flow=null",
        "data.val_scenarios=[drive]", "data.val_seeds=[1002]", "data.val_num_frames=3", "data.batch_size=2",
        "threads=1", "trainer.logger=false", "trainer.enable_progress_bar=false", "model.log_images_every=0"]


def _cfg(tmp_path: Path, *overrides: str):
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        return compose("train", overrides=[f"runs_dir={tmp_path}", *TINY, *overrides])


# ------------------------------------------------------------------------------------------------ the reference step
def _reference_augment(i1, i2, ff, fb, vf, vb, gen, gray_prob):
    """The retired loop's augmentation of a supervised batch (benchmarks/flow_training_run.py, verbatim logic)."""
    if torch.rand((), generator=gen) < 0.5:
        sign = torch.tensor([-1.0, 1.0]).view(1, 2, 1, 1)
        i1, i2, vf, vb = i1.flip(-1), i2.flip(-1), vf.flip(-1), vb.flip(-1)
        ff, fb = ff.flip(-1) * sign, fb.flip(-1) * sign
    gray = (torch.rand(i1.shape[0], 1, 1, 1, generator=gen) < gray_prob).float()
    luma = torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)

    def g(x):
        return gray * (x * luma).sum(1, keepdim=True).expand_as(x) + (1 - gray) * x

    both = torch.cat([g(i1), g(i2)])
    r = torch.rand(both.shape[0], 3, 1, 1, 1, generator=gen)
    b, c, gm = 0.8 + 0.4 * r[:, 0], 0.8 + 0.4 * r[:, 1], torch.exp((r[:, 2] - 0.5) * 0.45)
    mean = both.mean((1, 2, 3), keepdim=True)
    both = (((both - mean) * c + mean) * b).clamp(1e-4, 1).pow(gm)
    return (*both.split(i1.shape[0]), ff, fb, vf, vb)


def _reference_step(net, opt, sup, kitti, gen, lr, clip=10.0):
    """One step of the retired loop (benchmarks/flow_training_run.py, mixed phase) on a given batch; returns the loss
    and the gradient norm before clipping."""
    for group in opt.param_groups:
        group["lr"] = lr
    i1, i2, ff, fb, vf, vb = _reference_augment(*sup, gen=gen, gray_prob=0.3)
    flows_f, flows_b = net.forward_backward(i1, i2, all_scales=True)
    loss = 0.5 * (multiscale_epe(flows_f, ff, vf)[0] + multiscale_epe(flows_b, fb, vb)[0])
    k1, k2 = kitti
    if torch.rand((), generator=gen) < 0.5:
        k1, k2 = k1.flip(-1), k2.flip(-1)
    kf, kb = net.forward_backward(k1, k2, all_scales=True)
    loss = loss + 1.0 * self_supervised_flow_loss(k1, k2, kf, kb)[0]
    opt.zero_grad(set_to_none=True)
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
    opt.step()
    return float(loss.detach()), float(norm)


@pytest.fixture(scope="module")
def world() -> dict:
    return render_world(WorldRender(seed=3, scenario="highway", speed=(2.0, 3.0), frames=5, size=(32, 96), scale=2,
                                    skips=(1, 2), max_flow=None))


def test_one_lightning_step_equals_the_reference_step(tmp_path: Path, world: dict) -> None:
    """The same batch through FlowModule in a Lightning Trainer (mixed phase, augmentation, self-supervised pairs,
    gradient clipping (at 0.05 here, so that it acts), the phase's rate) and through the retired loop's step gives
    the same loss and weights."""
    pairs = SyntheticPairs([world])
    batch = {"step": torch.tensor(0), "sup": pairs.take(torch.tensor([0, 3, 5, 1])),
             "self": pairs.take(torch.tensor([2, 4]))}
    batch["self"] = {k: batch["self"][k] for k in ("image", "image_next")}
    cfg = _cfg(tmp_path, "model.phases=[{name: mix, steps: 5, lr: 2.0e-5, kitti: true}]", "data.seed=7",
               "model.grad_clip_norm=0.05")
    module = FlowModule(cfg)
    reference = FlowModule(cfg).net
    reference.load_state_dict(module.net.state_dict())
    opt = torch.optim.Adam(reference.parameters(), lr=2e-5)
    gen = step_generator(7, 0, 0, stream=1)  # the module's augmentation stream of step 0
    ref_loss, norm = _reference_step(reference, opt, tuple(batch["sup"][k] for k in (
        "image", "image_next", "flow_fwd", "flow_bwd", "flow_fwd_valid", "flow_bwd_valid")),
        (batch["self"]["image"], batch["self"]["image_next"]), gen, lr=2e-5, clip=0.05)
    assert norm > 0.05  # the clipping acts on this step

    trainer = L.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu", devices=1, limit_val_batches=0)
    trainer.fit(module, DataLoader([batch], batch_size=None))
    assert float(trainer.callback_metrics["train/loss"]) == pytest.approx(ref_loss, rel=1e-6)
    for (name, a), b in zip(module.net.named_parameters(), reference.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9, msg=name)
    assert any((a - b).abs().max() > 0 for a, b in zip(module.net.parameters(), FlowModule(cfg).net.parameters()))


@pytest.mark.parametrize("precision,by_trainer", [("32-true", False), ("bf16-mixed", False), ("bf16-mixed", True)])
def test_clipping_acts_with_the_fused_optimiser(tmp_path: Path, world: dict, precision: str, by_trainer: bool) -> None:
    """A clipped flow run steps with the fused Adam (no gradient scaler in fp32 or bf16; Lightning's bf16 plugin
    would refuse to clip for it) and its gradients reach the optimiser with the global norm clipped (0.05 here,
    below this step's norm: the previous test's batch), set by ``model.grad_clip_norm`` or by the trainer's
    ``gradient_clip_val`` with ``gradient_clip_algorithm`` named (Lightning passes it on as an enum). The step's
    gradients stay on the parameters after it."""
    pairs = SyntheticPairs([world])
    batch = {"step": torch.tensor(0), "sup": pairs.take(torch.tensor([0, 3, 5, 1])),
             "self": {k: v for k, v in pairs.take(torch.tensor([2, 4])).items() if k in ("image", "image_next")}}
    cfg = _cfg(tmp_path, "model.phases=[{name: mix, steps: 5, lr: 2.0e-5, kitti: true}]", "data.seed=7",
               f"model.grad_clip_norm={'null' if by_trainer else 0.05}")
    module = FlowModule(cfg)
    trainer = L.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, accelerator="cpu", devices=1, limit_val_batches=0,
                        precision=precision, gradient_clip_val=0.05 if by_trainer else None,
                        gradient_clip_algorithm="norm" if by_trainer else None)
    trainer.fit(module, DataLoader([batch], batch_size=None))
    assert trainer.optimizers[0].defaults["fused"]
    grads = [p.grad for p in module.net.parameters() if p.grad is not None]
    assert grads and float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads]))) <= 0.05 * (1 + 1e-5)


def test_schedule_is_step_based_per_phase(tmp_path: Path) -> None:
    """Each phase runs at its rate, /10 for its last quarter; the batch holds what the phase says."""
    cfg = _cfg(tmp_path, "model.phases=[{name: sup, steps: 8, lr: 1.0e-4}, {name: mix, steps: 4, lr: 2.0e-5, "
                         "kitti: true}]")
    module = FlowModule(cfg)
    lrs = [module.lr_at(s) for s in range(12)]
    assert lrs == pytest.approx([1e-4] * 6 + [1e-5] * 2 + [2e-5] * 3 + [2e-6])
    phases = module.phases
    assert [phase_at(phases, s)[0].name for s in (0, 7, 8, 11)] == ["sup", "sup", "mix", "mix"]
    module.trainer = None
    opt = module.configure_optimizers()
    sched = opt["lr_scheduler"]["scheduler"]
    seen = []
    for _ in range(12):
        seen.append(opt["optimizer"].param_groups[0]["lr"])
        opt["optimizer"].step()
        sched.step()
    assert seen == pytest.approx(lrs) and opt["lr_scheduler"]["interval"] == "step"


def test_a_cars_speed_leaves_the_hand_held_worlds_at_their_own_pace(tmp_path: Path) -> None:
    """``data.speed`` (m/frame) is a car's: the driving worlds take it, the hand-held ones move at their own pace
    (speed null), whatever it says; with ``data.speed=null`` every world is at its own pace."""
    sup = "model.phases=[{name: sup, steps: 2, lr: 1.0e-4}]"
    cfg = _cfg(tmp_path, sup, "data.seeds=[0,1,2,3]", "data.scenario=[drive,handheld,highway,handheld_planar]",
               "data.speed=[0.3,3.0]")
    renders = FlowMixDataModule(cfg)._renders()
    assert [(r.scenario, r.speed) for r in renders] == [("drive", (0.3, 3.0)), ("handheld", None),
                                                        ("highway", (0.3, 3.0)), ("handheld_planar", None)]
    own = FlowMixDataModule(_cfg(tmp_path, sup, "data.seeds=[0,1]", "data.scenario=[drive,handheld]",
                                 "data.speed=null"))._renders()
    assert [r.speed for r in own] == [None, None]


def test_render_cache_round_trip_and_the_flow_resizing(tmp_path: Path, world: dict) -> None:
    """A world render is the exact flow of the world block-averaged to the network size; the cache gives it back;
    a file of another format (the retired loop's) or another world is refused with one line naming it."""
    w = WorldRender(seed=3, scenario="highway", speed=(2.0, 3.0), frames=5, size=(32, 96), scale=2, skips=(1, 2),
                    max_flow=None)
    assert w.tag == "highway_s3_5f_32x96x2_sp(2.0, 3.0)_k12_mf_none".replace("mf_none", "mfnone")
    from dfvo.synthetic import SyntheticWorld
    sw = SyntheticWorld(seed=3, num_frames=5, height=64, width=192, scenario="highway", speed=(2.0, 3.0),
                        exposure_change=True, noise_std=0.02 * ((3 * 7919) % 11) / 10)
    k, j = (int(v) for v in world["pairs"][2])
    flow, valid = sw.flow(k, j)
    # the block average of the exact flow where all 4 pixels are valid, halved (pixels of the 32x96 image)
    blocks = flow.unfold(1, 2, 2).unfold(2, 2, 2).reshape(2, 32, 96, 4).mean(-1) / 2
    full = valid[0].unfold(0, 2, 2).unfold(1, 2, 2).reshape(32, 96, 4).all(-1)
    torch.testing.assert_close(world["flow_fwd"][2].float()[:, full], blocks[:, full], atol=2e-2, rtol=1e-3)
    assert torch.equal(world["valid_fwd"][2][0], full)
    ff, vv = downsample_flow(torch.ones(1, 2, 4, 4) * 3, torch.ones(1, 1, 4, 4, dtype=torch.bool), 2)
    assert torch.allclose(ff, torch.full((1, 2, 2, 2), 1.5)) and bool(vv.all())

    cached = cached_world(w, tmp_path)
    path = tmp_path / f"{w.tag}.pt"
    assert path.is_file() and cached["format"] == RENDER_FORMAT
    again = cached_world(w, tmp_path)
    assert torch.equal(again["images"], cached["images"]) and torch.equal(again["flow_bwd"], cached["flow_bwd"])
    torch.save({"images": cached["images"], "pairs": [], "scenario": "highway", "seed": 3}, path)  # the old format
    where = re.escape(str(path))
    with pytest.raises(RenderCacheError, match=rf"^render cache file {where} was written in another format \(none "
                                               r"recorded: written by the retired benchmarks/flow_training_run.py\); "
                                               r"this dfvo reads format 2: delete it") as err:
        cached_world(w, tmp_path)
    assert "\n" not in str(err.value)
    torch.save({**cached, "tag": "city_s9"}, path)
    with pytest.raises(RenderCacheError, match=r"holds 'city_s9', expected"):
        cached_world(w, tmp_path)
    path.write_bytes(b"not a torch file")
    with pytest.raises(RenderCacheError, match=rf"^render cache file {where} cannot be read"):
        cached_world(w, tmp_path)


def test_step_batches_depend_only_on_the_step(world: dict) -> None:
    from dfvo.training.config import FlowPhase
    pairs = SyntheticPairs([world])
    phases = [FlowPhase(name="sup", steps=3), FlowPhase(name="both", steps=2, kitti=True)]
    steps = FlowStepBatches(phases, pairs, pairs, batch_size=3, kitti_batch_size=2, seed=5)
    assert len(steps) == 5 and "self" not in steps[1] and set(steps[4]) == {"step", "sup", "self"}
    a, b = steps[4], FlowStepBatches(phases, pairs, pairs, 3, 2, seed=5)[4]
    assert torch.equal(a["sup"]["flow_fwd"], b["sup"]["flow_fwd"]) and torch.equal(a["self"]["image"],
                                                                                   b["self"]["image"])
    other_rank = FlowStepBatches(phases, pairs, pairs, 3, 2, seed=5, rank=1)[4]
    assert not torch.equal(a["sup"]["image"], other_rank["sup"]["image"])
    assert a["sup"]["image"].shape == (3, 3, 32, 96) and a["sup"]["flow_fwd_valid"].dtype == torch.bool


# ------------------------------------------------------------------------------------------------ runs
def _weights(out: dict) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in out["module"].net.state_dict().items()}


def test_mixed_run_validates_and_resumes_exactly_across_a_phase_boundary(tmp_path: Path,
                                                                          kitti_raw_root: Path) -> None:
    """sup 2 + mix 3 steps with KITTI raw pairs: the run logs the held-out metrics (val/epe per scenario, selected
    correspondences), and a run stopped at step 3 (inside the mixed phase) and resumed from last.ckpt ends with the
    same weights, bitwise, as the uninterrupted run."""
    common = ["model.phases=[{name: sup, steps: 2, lr: 1.0e-4}, {name: mix, steps: 3, lr: 2.0e-5, kitti: true}]",
              f"data.root={kitti_raw_root.parent}", "data.drives=[2011_09_26_drive_0001]", "data.kitti_batch_size=1",
              "trainer.checkpoint_every_n_steps=2", f"data.cache_dir={tmp_path / 'cache'}"]
    full = run_training(_cfg(tmp_path, *common, "name=full"))
    assert full["global_step"] == 5
    m = full["metrics"]
    assert {"val/epe", "val/epe/drive", "val/epe_selected", "val/epe_selected/drive", "train/self_loss"} <= set(m)
    assert m["val/epe"] == pytest.approx(m["val/epe/drive"]) and 0 < m["val/epe_selected"] < 200
    first = run_training(_cfg(tmp_path, *common, "name=part", "trainer.max_steps=3"))
    assert first["global_step"] == 3
    last = tmp_path / "part" / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == 3
    resumed = run_training(_cfg(tmp_path, *common, "name=part", f"ckpt_path={last}"))
    assert resumed["global_step"] == 5
    for key, value in _weights(full).items():
        assert torch.equal(value, _weights(resumed)[key]), key


def test_held_out_validation_is_the_inference_path(tmp_path: Path) -> None:
    """The held-out AEPE of the module equals NetworkFlow's flow (inference: resize in, resize back) against the
    world's exact flow, and the selected correspondences' error is computed at the best-N pixels."""
    from dfvo.sources.networks import NetworkFlow
    from dfvo.training.flow_renders import heldout_set
    cfg = _cfg(tmp_path, "model.phases=[{name: sup, steps: 1}]")
    module = FlowModule(cfg).eval()
    s = heldout_set("drive", [1002], 3, (64, 192), 1, None)
    visible, selected = module.heldout_errors(s)
    weights = tmp_path / "w.safetensors"
    from dfvo.io.checkpoint import save_weights
    save_weights(module.net, weights, {"task": "flow", "variant": "tiny", "height": 32, "width": 96},
                 dtype=torch.float32)
    fwd, _ = NetworkFlow(weights)(s["image"], s["image_next"])
    err = (fwd - s["flow"]).norm(dim=1, keepdim=True)[s["valid"]]
    torch.testing.assert_close(visible, err, rtol=1e-5, atol=1e-5)
    assert 0 < len(selected) <= 2 * 2000


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_input_stops_with_one_line(tmp_path: Path) -> None:
    """A KITTI raw root without the layout (before minutes of rendering), a depth checkpoint as the flow model's
    init_from, and a flow model on data of another kind each stop before training with one line naming the file or
    setting."""
    empty = tmp_path / "empty"
    empty.mkdir()
    mix = "model.phases=[{name: mix, steps: 2, kitti: true}]"
    with pytest.raises(ValueError, match=rf"^data=flow_mix \(data.root={empty}\): KITTI raw root {empty} contains no "
                                         r"DATE/DATE_drive_XXXX_sync folders") as err:
        run_training(_cfg(tmp_path, mix, f"data.root={empty}", "name=x", f"data.cache_dir={tmp_path / 'cache'}"))
    assert "\n" not in str(err.value) and not (tmp_path / "x" / "checkpoints").exists()
    assert not (tmp_path / "cache").exists()  # refused before any world was rendered

    from dfvo.io.checkpoint import CheckpointError, save_weights
    from dfvo.models.depth_net import DepthNet
    depth = tmp_path / "depth.safetensors"
    save_weights(DepthNet(), depth, {"task": "depth"})
    with pytest.raises(CheckpointError, match=rf"^model.init_from={depth}: holds a depth model .*expected a flow "
                                              "network"):
        FlowModule(_cfg(tmp_path, f"model.init_from={depth}"))
    with pytest.raises(ValueError, match="data=flow_mix gives step batches of the phases of model=flow_mix"):
        FlowMixDataModule(_cfg(tmp_path, "model=flow_supervised"))
    with pytest.raises(ValueError, match="model.phases: mode 'mixed'"):
        FlowModule(_cfg(tmp_path, "model.phases=[]"))


def test_resume_from_another_model_kind_is_refused(tmp_path: Path) -> None:
    first = run_training(_cfg(tmp_path, "model.phases=[{name: sup, steps: 1}]", "data.val_seeds=[]", "name=f",
                              "data.max_train_samples=4"))
    with pytest.raises(ValueError, match=r"ckpt_path=.*holds a 'flow:flow_mix' model, but this run is "
                                         r"'depth:depth_stereo'"):
        with initialize_config_module("dfvo.conf.train", version_base="1.3"):
            cfg = compose("train", overrides=[f"runs_dir={tmp_path}", f"ckpt_path={first['last_ckpt']}", "name=d"])
        run_training(cfg)
    assert OmegaConf.select(cfg, "model.name") == "depth_stereo"


# ------------------------------------------------------------------------------------------------ distillation
def test_distillation_is_the_teachers_flow_and_teaches_it(tmp_path: Path, world: dict) -> None:
    """``model.teacher`` (the shipped network): a student with the teacher's own weights has a finest-scale
    distillation EPE of 0 on the KITTI pairs; a fresh tiny student's is large and falls when trained on the
    distillation alone; the teacher is in neither the checkpointed state nor the optimised parameters."""
    teacher_file = "checkpoints/flow.safetensors"
    pairs = SyntheticPairs([world])
    k = pairs.take(torch.tensor([2, 4]))
    batch = {"step": torch.tensor(0), "self": {"image": k["image"], "image_next": k["image_next"]}}
    distil = (f"model.teacher={teacher_file}", "model.w_distill=1.0", "model.self_weight=0",
              "model.phases=[{name: mix, steps: 5, lr: 1.0e-3, synthetic: false, kitti: true}]")

    same = FlowModule(_cfg(tmp_path, *distil, "model.variant=small"))
    same.net.load_state_dict(same.teacher().state_dict())
    _, terms, _ = same.mixed_loss(batch, None)
    assert float(terms["distill_epe"]) < 1e-5

    student = FlowModule(_cfg(tmp_path, *distil))
    assert not any("teacher" in key for key in student.state_dict())
    assert sum(p.numel() for p in student.parameters()) == sum(p.numel() for p in student.net.parameters())
    with torch.no_grad():
        target = student.teacher().forward_backward(batch["self"]["image"], batch["self"]["image_next"])
    assert float(flow_magnitude(target[0]).mean()) > 0.5  # something to learn
    opt = torch.optim.Adam(student.net.parameters(), lr=1e-3)
    first = None
    for _ in range(40):
        loss, terms, _ = student.mixed_loss(batch, None)
        first = float(terms["distill_epe"]) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert first > 0.3 and float(terms["distill_epe"]) < 0.5 * first
    assert any(p.grad is not None for p in student.net.parameters())
    assert all(p.grad is None for p in student.teacher().parameters())


def test_a_teacher_needs_kitti_pairs_and_a_weight(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"^model.teacher=t.safetensors: the teacher supervises the KITTI pairs"):
        FlowModule(_cfg(tmp_path, "model.teacher=t.safetensors", "model.w_distill=1",
                        "model.phases=[{name: sup, steps: 2}]"))
    with pytest.raises(ValueError, match=r"^model.w_distill=1.0 needs model.teacher"):
        FlowModule(_cfg(tmp_path, "model.w_distill=1"))
    with pytest.raises(ValueError, match=r"^model.teacher=t.safetensors has no effect with model.w_distill=0.0"):
        FlowModule(_cfg(tmp_path, "model.teacher=t.safetensors"))
