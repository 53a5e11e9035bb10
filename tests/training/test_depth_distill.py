"""Narrower depth networks (``model.width_multiplier``) and distillation from a trained one (``model.teacher``)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from safetensors.torch import save_file

from dfvo.losses.depth_supervision import log_depth_l1
from dfvo.models.depth_net import DepthNet, network_width
from dfvo.synthetic import SyntheticWorld
from dfvo.training.augment import augment_depth_batch

H, W = 64, 192


def conv_multiply_adds(net: DepthNet, h: int = 96, w: int = 320) -> int:
    """Multiply-adds of every convolution of ``net``'s training forward on one (1,3,h,w) image, counted by hooks
    from each layer's weight shape and output size."""
    total = 0

    def count(module: torch.nn.Conv2d, args: tuple, out: torch.Tensor) -> None:
        nonlocal total
        total += out.numel() * module.weight[0].numel()

    hooks = [m.register_forward_hook(count) for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        net(torch.rand(1, 3, h, w))
    for hook in hooks:
        hook.remove()
    return total


def test_half_width_network_has_a_quarter_of_the_work_and_the_same_outputs() -> None:
    """width=0.5 halves every layer (encoder 32..256 channels, decoder 8..128) and so needs about a quarter of the
    multiply-adds (every convolution's cost is in_channels x out_channels; the 3-channel input and the 1-channel
    heads do not halve); its outputs have the full network's shapes and range."""
    full, half = DepthNet(), DepthNet(width=0.5)
    assert full.encoder.num_ch_enc == (64, 64, 128, 256, 512)
    assert half.encoder.num_ch_enc == (32, 32, 64, 128, 256)
    assert [b.conv.out_channels for b in half.decoder.up1] == [8, 16, 32, 64, 128]
    ratio = conv_multiply_adds(half) / conv_multiply_adds(full)
    assert 0.25 <= ratio < 0.30, ratio
    x = torch.rand(2, 3, 64, 96)
    out_full, out_half = full(x), half(x)
    assert {s: v.shape for s, v in out_full.items()} == {s: v.shape for s, v in out_half.items()}
    with pytest.raises(ValueError, match="network width"):
        DepthNet(width=0.0)


def test_a_narrow_networks_file_loads_as_what_it_was(tmp_path: Path) -> None:
    """A half-width network exported with its ``width_multiplier`` runs as the depth source exactly as the network
    itself does; a file whose record is not a positive number is refused with one line naming the setting."""
    from dfvo.sources.networks import NetworkDepth

    torch.manual_seed(0)
    net = DepthNet(width=0.5).eval()
    path = tmp_path / "small.safetensors"
    meta = {"task": "depth", "min_depth": "0.1", "max_depth": "100.0", "width_multiplier": "0.5"}
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(path), metadata=meta)
    source = NetworkDepth(path, input_size=(64, 96))
    assert source.model.width == 0.5
    image = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        torch.testing.assert_close(source.network_depth(image), net.depth(image))
    plain = tmp_path / "plain.safetensors"  # no metadata (a plain state dict): the width read off the first layer
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(plain))
    assert NetworkDepth(plain, input_size=(64, 96)).model.width == 0.5
    # a training checkpoint's state: the pose network's encoder beside the depth network's, in either order
    half, pose = DepthNet(width=0.5).state_dict(), DepthNet().encoder.state_dict()
    mixed = {**{f"pose_net.encoder.{k}": v for k, v in pose.items()}, **{f"depth_net.{k}": v for k, v in half.items()}}
    assert network_width({}, "depth.checkpoint", mixed) == 0.5
    bad = tmp_path / "bad.safetensors"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(bad), metadata={**meta,
                                                                                            "width_multiplier": "-1"})
    with pytest.raises(ValueError, match="depth.checkpoint: .*width_multiplier.*'-1'"):
        NetworkDepth(bad)


@pytest.fixture(scope="module")
def sample() -> dict:
    """One synthetic stereo + temporal sample."""
    world = SyntheticWorld(seed=0, num_frames=6, height=H, width=W, scenario="straight")
    f = world.render(2, right=True, flow=True)
    return {"image": f["image"][None], "image_right": f["image_right"][None], "image_next": world.image(3)[None],
            "image_prev": world.image(1)[None], "K": f["K"][None].float(),
            "T_right_left": f["T_right_left"][None].float()}


def _module(teacher: Path, width: float, augment: dict | None = None, **model):
    """A depth module distilled from ``teacher``; ``model``: further ``model.`` settings."""
    from dfvo.training.depth_module import DepthPoseModule

    cfg = OmegaConf.create({"model": {"task": "depth", "name": "depth_stereo", "init_depth": 10.0,
                                      "width_multiplier": width, "teacher": str(teacher), "w_distill": 1.0,
                                      "w_depth_supervised": 1.0, "augment": augment, **model},
                            "data": {"seed": 0, "camera_height": 1.65}})
    return DepthPoseModule(cfg).eval()


def _teacher(tmp_path: Path, seed: int) -> tuple[DepthNet, Path]:
    """A teacher whose depth varies over the image (the untrained network's is nearly flat), in inference mode, and
    its weights file."""
    torch.manual_seed(seed)
    teacher_net = DepthNet(init_depth=10.0)
    with torch.no_grad():
        teacher_net.decoder.heads[0].conv.weight.normal_(0.0, 0.5)
    teacher_net.eval()
    return teacher_net, _save(teacher_net, tmp_path / "teacher.safetensors")


def _save(net: DepthNet, path: Path) -> Path:
    meta = {"task": "depth", "min_depth": "0.1", "max_depth": "100.0", "width_multiplier": repr(net.width)}
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(path), metadata=meta)
    return path


def test_distillation_term_is_the_students_distance_to_the_teacher(tmp_path: Path, sample: dict) -> None:
    """The distillation term at scale 0 is the log-depth L1 between the student's depth and the teacher's: ~0 for a
    student that is the teacher (same width, same weights), the hand-computed value for a half-width student. The
    teacher is in neither the checkpoint's state dict nor the optimiser."""
    teacher_net, path = _teacher(tmp_path, 3)

    same = _module(path, 1.0)
    same.depth_net.load_state_dict(teacher_net.state_dict())
    with torch.no_grad():
        _, terms, _ = same._losses(sample, None)
    assert float(terms["distill_s0"]) < 1e-5, terms["distill_s0"]

    student = _module(path, 0.5)
    with torch.no_grad():
        _, terms, _ = student._losses(sample, None)
        expected, _ = log_depth_l1(student(sample["image"]), teacher_net.depth(sample["image"]), 100.0)
    assert float(terms["distill_s0"]) > 0.05
    torch.testing.assert_close(terms["distill_s0"], expected, rtol=1e-4, atol=1e-6)
    assert not any("teacher" in k for k in student.state_dict())
    assert student.export_network()[1]["width_multiplier"] == "0.5"
    optimiser = student.configure_optimizers()
    optimiser = optimiser["optimizer"] if isinstance(optimiser, dict) else optimiser
    optimiser = optimiser[0][0] if isinstance(optimiser, tuple) else optimiser
    trained = {id(p) for group in optimiser.param_groups for p in group["params"]}
    assert trained and all(id(p) not in trained for p in student.teacher().parameters())
    assert {id(p) for p in student.depth_net.parameters()} <= trained


def test_the_teacher_sees_the_image_without_shadows(tmp_path: Path, sample: dict) -> None:
    """With ``augment.shadow_prob=1`` the student sees the shadowed image and the teacher the same image without the
    shadows, so the student is taught the depth of the scene, not of its shadows."""
    path = _save(DepthNet(init_depth=10.0).eval(), tmp_path / "teacher.safetensors")
    module = _module(path, 0.5, {"flip_prob": 0.0, "jitter_prob": 0.0, "shadow_prob": 1.0})
    seen: dict[str, torch.Tensor] = {}

    def student_input(m: torch.nn.Module, args: tuple, out: object) -> None:
        seen.setdefault("student", args[0])

    module.depth_net.register_forward_hook(student_input)
    teacher = module.teacher()
    original = teacher.disparity

    def record(image: torch.Tensor) -> torch.Tensor:
        seen.setdefault("teacher", image)
        return original(image)

    teacher.disparity = record
    with torch.no_grad():
        module.training_step(sample, 0)
    _, net = augment_depth_batch(sample, module.augment, torch.Generator().manual_seed(0))
    assert torch.equal(seen["student"][:1], net["image_depth"])
    assert torch.allclose(seen["teacher"], sample["image"], atol=1e-6)
    assert (net["image_depth"] < sample["image"] - 1e-3).any()


def test_the_teacher_sees_the_scene_without_pasted_objects_and_skips_their_pixels(tmp_path: Path,
                                                                                  sample: dict) -> None:
    """With ``augment.paste_prob=1`` the student sees the objects and is supervised at their known depth; the teacher
    sees the image as it was and teaches every other pixel: the distillation term is the log-depth L1 against the
    teacher's depth of the unpasted image with the object pixels left out (hand-computed here), which differs from
    the term over every pixel of the pasted image by more than the tolerance."""
    teacher_net, path = _teacher(tmp_path, 5)
    module = _module(path, 0.5, {"flip_prob": 0.0, "jitter_prob": 0.0, "paste_prob": 1.0, "paste_max": 3,
                                 "paste_depth": [3.0, 6.0]})
    real = {**sample, "camera_height": torch.tensor([1.65])}  # a real sample: objects are pasted
    batch, net = augment_depth_batch(real, module.augment, torch.Generator().manual_seed(0))
    pasted = batch["pasted"]
    assert 0.02 < float(pasted.float().mean()) < 0.9 and not torch.equal(batch["image"], sample["image"])
    assert torch.allclose(net["image_unpasted"], sample["image"], atol=1e-6)  # no jitter drawn: the image as it was
    with torch.no_grad():
        _, terms, _ = module._losses(batch, net)
        student = module(batch["image"])
        behind = teacher_net.depth(sample["image"])
        expected, count = log_depth_l1(student, behind.masked_fill(pasted, 0.0), 100.0)
        everywhere, _ = log_depth_l1(student, teacher_net.depth(batch["image"]), 100.0)
    assert int(count) == pasted.numel() - int(pasted.sum())
    torch.testing.assert_close(terms["distill_s0"], expected, rtol=1e-4, atol=1e-6)
    assert abs(float(everywhere) - float(expected)) > 1e-2 * float(expected)
    assert "depth_supervised_s0" in terms  # the objects' own depth teaches their pixels


def test_the_teacher_can_be_left_to_the_pixels_without_another_target(tmp_path: Path, sample: dict) -> None:
    """``model.distill_where_no_target``: the distillation term averages the teacher's log-depth L1 over the pixels
    without true depth or a stereo hint only (hand-computed), not over every pixel."""
    teacher_net, path = _teacher(tmp_path, 7)
    module = _module(path, 0.5)
    targeted = _module(path, 0.5, distill_where_no_target=True)
    targeted.load_state_dict(module.state_dict())
    truth = torch.zeros(1, 1, H, W)
    truth[..., : H // 3, :] = 20.0  # the top third has true depth, the left half of the rest a hint
    hint = torch.zeros(1, 1, H, W)
    hint[..., H // 3:, : W // 2] = 8.0
    batch = {**sample, "depth": truth, "depth_hint": hint}
    with torch.no_grad():
        _, every, _ = module._losses(batch, None)
        _, left, _ = targeted._losses(batch, None)
        student, teacher = module(sample["image"]), teacher_net.depth(sample["image"])
        free = (truth <= 0) & (hint <= 0)
        expected, count = log_depth_l1(student, teacher.masked_fill(~free, 0.0), 100.0)
        everywhere, _ = log_depth_l1(student, teacher, 100.0)
    assert int(count) == int(free.sum()) == (H - H // 3) * (W - W // 2)
    torch.testing.assert_close(left["distill_s0"], expected, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(every["distill_s0"], everywhere, rtol=1e-4, atol=1e-6)
    assert abs(float(expected) - float(everywhere)) > 1e-2 * float(everywhere)


def test_hints_can_be_kept_to_the_lower_rows_with_the_teacher_above(tmp_path: Path, sample: dict) -> None:
    """``model.depth_hints_from_row``: the hints above that fraction of the height are dropped before any loss, so
    every term (the hint term, and with ``distill_where_no_target`` the teacher's, which takes those pixels) equals
    the same module's on a batch whose hint was zeroed there by hand, and differs from the terms with every hint."""
    _, path = _teacher(tmp_path, 5)

    def module(from_row: float):
        return _module(path, 1.0, w_depth_hints=1.0, distill_where_no_target=True, depth_hints_from_row=from_row)

    rows, every_row = module(2 / 3), module(0.0)
    rows.load_state_dict(every_row.state_dict())
    hint = torch.full((1, 1, H, W), 8.0)
    hint[..., :, : W // 4] = 0.0  # no match on the left quarter
    by_hand = hint.clone()
    by_hand[..., : round(2 / 3 * H), :] = 0.0
    with torch.no_grad():
        loss_kept, kept, _ = rows._losses({**sample, "depth_hint": hint}, None)
        loss_zeroed, zeroed, _ = every_row._losses({**sample, "depth_hint": by_hand}, None)
        _, everywhere, _ = every_row._losses({**sample, "depth_hint": hint}, None)
    torch.testing.assert_close(loss_kept, loss_zeroed, rtol=1e-5, atol=1e-7)
    for key in ("depth_hints_s0", "distill_s0"):
        torch.testing.assert_close(kept[key], zeroed[key], rtol=1e-5, atol=1e-7)
    assert float(kept["depth_hints_used_s0"]) < float(everywhere["depth_hints_used_s0"])
    assert abs(float(kept["distill_s0"]) - float(everywhere["distill_s0"])) > 1e-3 * float(everywhere["distill_s0"])
    with pytest.raises(ValueError, match="model.depth_hints_from_row=1.0"):
        module(1.0)


def test_the_teacher_can_take_the_stereo_hints_scale(tmp_path: Path, sample: dict) -> None:
    """``model.distill_scale_from_hints``: with hints 1.3x the teacher's depth on every row and ``depth_hints_from_row``
    2/3, a student that is the teacher sees its distillation term become log 1.3 on the rows above (the teacher's
    depth x the median hint / teacher there, which is 1.3), where without the setting it is ~0; the hints of the
    rows below, which the hint term takes, do not count twice; a batch without hints keeps the teacher's scale. The
    per-image scale: the median over the pixels with both, 1 for an image with too few. (Without a teacher the
    setting is refused: test_distillation_settings_are_checked.)"""
    from dfvo.training.depth_module import MIN_SCALE_PIXELS, teacher_scaled_to_hints

    teacher_net, path = _teacher(tmp_path, 11)
    settings = {"w_depth_hints": 1.0, "distill_where_no_target": True, "depth_hints_from_row": 2 / 3}
    plain, scaled = _module(path, 1.0, **settings), _module(path, 1.0, distill_scale_from_hints=True, **settings)
    for module in (plain, scaled):
        module.depth_net.load_state_dict(teacher_net.state_dict())
    with torch.no_grad():
        hint = 1.3 * teacher_net.depth(sample["image"])
        _, same, _ = plain._losses({**sample, "depth_hint": hint}, None)
        _, taught, _ = scaled._losses({**sample, "depth_hint": hint}, None)
    assert float(same["distill_s0"]) < 1e-5
    assert float(taught["distill_s0"]) == pytest.approx(float(torch.tensor(1.3).log()), rel=1e-3)
    unhinted_module = _module(path, 1.0, distill_scale_from_hints=True, distill_where_no_target=True)
    unhinted_module.depth_net.load_state_dict(teacher_net.state_dict())
    with torch.no_grad():  # a batch without hints (a batch of synthetic worlds): the teacher's own scale
        _, unhinted, _ = unhinted_module._losses(sample, None)
    assert float(unhinted["distill_s0"]) < 1e-5

    teacher = torch.full((2, 1, 4, 50), 10.0)
    hints = torch.zeros(2, 1, 4, 50)
    hints[0, :, :3] = torch.linspace(5.0, 40.0, 150).view(3, 50)  # median ~22.5 over 150 pixels: x2.25
    hints[1, :, 0, : MIN_SCALE_PIXELS // 4] = 30.0  # too few pixels: x1
    out = teacher_scaled_to_hints(teacher.masked_fill(torch.arange(4).view(1, 1, 4, 1) == 3, 0.0), hints)
    assert float(hints[0, :, :3].median()) == pytest.approx(22.5, abs=0.15)
    torch.testing.assert_close(out[0, :, :3], torch.full((1, 3, 50), float(hints[0, :, :3].median())))  # 10 x 2.25
    assert float(out[0, :, 3].abs().max()) == 0.0  # no target stays no target
    torch.testing.assert_close(out[1, :, :3], torch.full((1, 3, 50), 10.0))


def test_distillation_settings_are_checked() -> None:
    """w_distill without a teacher, a teacher without a weight, the teacher's scale from hints without a teacher, a
    channel multiplier that is an image width: one line naming the key."""
    from dfvo.training.config import DepthModelConfig

    with pytest.raises(ValueError, match="model.w_distill=1.0 needs model.teacher"):
        DepthModelConfig(name="depth_stereo", w_distill=1.0)
    with pytest.raises(ValueError, match="model.distill_scale_from_hints=true scales the teacher's depth"):
        DepthModelConfig(name="depth_stereo", distill_scale_from_hints=True)
    with pytest.raises(ValueError, match="model.width_multiplier=320"):
        DepthModelConfig(name="depth_stereo", width_multiplier=320)
    with pytest.raises(ValueError, match="model.teacher=t.safetensors has no effect"):
        DepthModelConfig(name="depth_stereo", teacher="t.safetensors")
