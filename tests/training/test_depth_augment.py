"""Depth training augmentation: mirrored batches keep the stereo/temporal geometry exact; jitter is deterministic."""

from __future__ import annotations

import pytest
import torch

from dfvo.losses.photometric import ssim_l1_error
from dfvo.losses.reprojection import reproject
from dfvo.synthetic import SyntheticWorld
from dfvo.training.augment import DepthAugmentConfig, augment_depth_batch, flip_batch, jitter_images

H, W = 64, 192


@pytest.fixture(scope="module")
def batch() -> dict:
    """One synthetic stereo + temporal sample with its true depth and true T_next_cur."""
    world = SyntheticWorld(seed=0, num_frames=6, height=H, width=W, scenario="straight")
    f = world.render(2, right=True, flow=True)
    poses = world.poses()
    return {"image": f["image"][None], "image_right": f["image_right"][None], "image_next": world.image(3)[None],
            "K": f["K"][None].float(), "T_right_left": f["T_right_left"][None].float(), "depth": f["depth"][None],
            "T_next_cur": (torch.linalg.inv(poses[3]) @ poses[2]).float()[None],
            "static": (~f["dynamic_mask"] & (f["depth"] < 999))[None], "visible_next": f["flow_fwd_valid"][None]}


def _warp_error(b: dict, source: str, T: torch.Tensor) -> float:
    rep = reproject(b[source], b["depth"], T, b["K"])
    err = ssim_l1_error(b["image"], rep.warped)
    m = rep.valid & b["static"]
    if source == "image_next":  # occlusions are the per-pixel minimum's job, not this test's
        m &= b["visible_next"]
    return float(err[m].median())


@pytest.mark.parametrize("source,T_key", [("image_right", "T_right_left"), ("image_next", "T_next_cur")])
def test_flipped_sample_warps_as_exactly_as_the_original(batch: dict, source: str, T_key: str) -> None:
    """With the true depth, the mirrored sample (cx -> W-1-cx, stereo x translation negated) warps its source view
    onto its target as well as the original does; keeping the unflipped K or T does not."""
    flipped = flip_batch(batch, torch.tensor([True]))
    flipped["static"] = batch["static"].flip(-1)
    flipped["visible_next"] = batch["visible_next"].flip(-1)
    assert torch.equal(flipped["image"], batch["image"].flip(-1))
    assert torch.isclose(flipped["K"][0, 0, 2], (W - 1) - batch["K"][0, 0, 2])
    T = flipped[T_key] if T_key == "T_right_left" else batch[T_key].clone()
    if T_key == "T_next_cur":  # mirroring the world conjugates the motion by diag(-1, 1, 1)
        M = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
        T = M @ T @ M
    original = _warp_error(batch, source, batch[T_key])
    mirrored = _warp_error(flipped, source, T)
    assert original < 5e-3 and mirrored < 5e-3
    assert abs(mirrored - original) < 2e-3
    if T_key == "T_right_left":  # the un-negated baseline puts the partner camera on the wrong side
        assert _warp_error(flipped, source, batch[T_key]) > 3 * max(mirrored, 1e-3)


def test_flip_and_jitter_are_drawn_per_sample(batch: dict) -> None:
    """In a batch of two, only the flagged sample is mirrored, and each sample gets its own colour draw."""
    two = {k: torch.cat([v, v]) for k, v in batch.items()}
    out = flip_batch(two, torch.tensor([True, False]))
    assert torch.equal(out["image"][0], two["image"][0].flip(-1)) and torch.equal(out["image"][1], two["image"][1])
    assert out["K"][0, 0, 2] != two["K"][0, 0, 2] and out["K"][1, 0, 2] == two["K"][1, 0, 2]
    assert out["T_right_left"][0, 0, 3] == -two["T_right_left"][0, 0, 3]
    assert out["T_right_left"][1, 0, 3] == two["T_right_left"][1, 0, 3]
    jit = jitter_images({"image": two["image"]}, DepthAugmentConfig(jitter_prob=1.0), torch.Generator().manual_seed(1))
    assert not torch.allclose(jit["image"][0], jit["image"][1], atol=1e-3)


def test_jitter_is_shared_by_a_samples_images_and_reproducible(batch: dict) -> None:
    cfg = DepthAugmentConfig(flip_prob=0.0, jitter_prob=1.0, gray_prob=0.0)
    images = {"image": batch["image"], "image_right": batch["image"]}
    a = jitter_images(images, cfg, torch.Generator().manual_seed(3))
    b = jitter_images(images, cfg, torch.Generator().manual_seed(3))
    assert torch.equal(a["image"], b["image"])  # same seed, same draw
    assert torch.equal(a["image"], a["image_right"])  # one draw per sample, applied to all its images
    assert (a["image"] - batch["image"]).abs().mean() > 1e-3
    assert a["image"].min() >= 0 and a["image"].max() <= 1
    none = jitter_images(images, DepthAugmentConfig(jitter_prob=0.0), torch.Generator().manual_seed(3))
    assert torch.allclose(none["image"], batch["image"], atol=1e-5)
    gray = jitter_images(images, DepthAugmentConfig(jitter_prob=0.0, gray_prob=1.0), torch.Generator())["image"]
    assert torch.allclose(gray[:, 0], gray[:, 1]) and torch.allclose(gray[:, 1], gray[:, 2])
    luma = (batch["image"] * torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1)
    assert torch.allclose(gray[:, 0], luma, atol=1e-5)


def test_augment_batch_only_jitters_network_inputs(batch: dict) -> None:
    cfg = DepthAugmentConfig(flip_prob=0.0, jitter_prob=1.0)
    out, net = augment_depth_batch(batch, cfg, torch.Generator().manual_seed(0))
    assert torch.equal(out["image"], batch["image"])  # the losses see the real images
    assert set(net) == {"image", "image_right", "image_next"}
    assert (net["image"] - batch["image"]).abs().mean() > 1e-3


def test_bad_settings_name_the_key() -> None:
    with pytest.raises(ValueError, match="model.augment.flip_prob"):
        DepthAugmentConfig(flip_prob=1.5)
    with pytest.raises(ValueError, match="model.augment.hue"):
        DepthAugmentConfig(hue=0.7)


def _module_seeing_inputs(batch: dict, augment: dict) -> tuple:
    """A stereo + temporal DepthPoseModule with ``model.augment`` settings ``augment``, a training sample of
    ``batch``, and the dict the first input of its depth network (``depth``) and the target image of its pose network
    (``pose``) are recorded in."""
    from omegaconf import OmegaConf

    from dfvo.training.depth_module import DepthPoseModule

    cfg = OmegaConf.create({"model": {"task": "depth", "name": "depth_stereo", "stereo": True, "temporal": True,
                                      "init_depth": 10.0, "augment": augment}, "data": {"seed": 0}})
    module = DepthPoseModule(cfg).eval()
    sample = {k: batch[k] for k in ("image", "image_right", "image_next", "K", "T_right_left")}
    sample["image_prev"] = batch["image_next"]
    seen: dict[str, torch.Tensor] = {}

    def record(name: str, position: int):
        def hook(module: torch.nn.Module, args: tuple, output: object) -> None:
            seen.setdefault(name, args[position])
        return hook

    module.depth_net.register_forward_hook(record("depth", 0))
    module.pose_net.register_forward_hook(record("pose", 1))
    return module, sample, seen


def test_depth_module_feeds_jittered_images_to_the_networks_and_plain_ones_to_the_losses(batch: dict) -> None:
    """With jitter on, the depth and pose networks see the jittered inputs while the photometric terms compare the
    real images: the loss equals the loss of the same network inputs computed by hand from the plain batch."""
    module, sample, seen = _module_seeing_inputs(batch, {"flip_prob": 0.0, "jitter_prob": 1.0})
    with torch.no_grad():
        loss = module.training_step(sample, 0)
        _, net = augment_depth_batch(sample, module.augment, torch.Generator().manual_seed(0 * 1009 + 0))
        expected, _, _ = module._losses(sample, net)
    assert torch.equal(seen["depth"], net["image"]) and not torch.allclose(seen["depth"], sample["image"])
    assert torch.equal(seen["pose"], net["image"])  # PoseNet(prev, image): the target frame is jittered too
    torch.testing.assert_close(loss, expected)
    with torch.no_grad():
        plain, _, _ = module._losses(sample, None)
    assert not torch.allclose(loss, plain)  # the networks' inputs changed the prediction, not the loss targets


def test_shadows_darken_only_the_drawn_samples_by_the_drawn_factor(batch: dict) -> None:
    """A shadowed pixel keeps ``f`` of its light (f within shadow_factor), an unshadowed one all of it; samples not
    drawn are returned as they are; the same generator seed gives the same shadows."""
    from dfvo.training.augment import cast_shadows, shadow_masks

    image = torch.cat([batch["image"]] * 8)
    cfg = DepthAugmentConfig(shadow_prob=0.5, shadow_factor=(0.4, 0.6))
    out = cast_shadows(image, cfg, torch.Generator().manual_seed(5))
    assert torch.equal(out, cast_shadows(image, cfg, torch.Generator().manual_seed(5)))
    ratio = torch.where(image > 0.05, out / image.clamp_min(1e-6), torch.ones_like(image))
    assert ratio.min() >= 0.4 - 1e-6 and ratio.max() <= 1 + 1e-6
    changed = (ratio < 0.999).flatten(1).any(1)
    assert 0 < int(changed.sum()) < 8  # p = 0.5 over 8 samples with this seed: some, not all
    for b in range(8):
        if changed[b]:
            darkest = float(ratio[b].min())
            assert 0.4 - 1e-6 <= darkest <= 0.6 + 1e-3  # the shadow's core keeps f of the light
            assert float((ratio[b] < 0.999).float().mean()) < 0.95  # a region, not the whole image
        else:
            assert torch.equal(out[b], image[b])
    masks = shadow_masks(64, H, W, torch.Generator().manual_seed(0))
    assert masks.min() >= 0 and masks.max() <= 1
    cover = (masks > 0.5).flatten(1).float().mean(1)
    assert float(cover.min()) > 0.0 and float(cover.median()) < 0.7  # every sample has a shadow, few cover it all
    with pytest.raises(ValueError, match="model.augment.shadow_factor"):
        DepthAugmentConfig(shadow_factor=(0.8, 0.3))
    with pytest.raises(ValueError, match="model.augment.shadow_prob"):
        DepthAugmentConfig(shadow_prob=2.0)
    with pytest.raises(ValueError, match="model.augment.shadow_factor"):
        DepthAugmentConfig(shadow_factor=(0.5,))


def test_shadows_reach_the_depth_network_only_and_keep_the_other_draws(batch: dict) -> None:
    """With shadow_prob > 0 the depth network sees ``image_depth`` (the jittered image with shadows), the pose
    network and the losses the images without; flips and jitter are drawn as without shadows."""
    plain_cfg = DepthAugmentConfig(flip_prob=0.5, jitter_prob=1.0)
    shadow_cfg = DepthAugmentConfig(flip_prob=0.5, jitter_prob=1.0, shadow_prob=1.0)
    out_a, net_a = augment_depth_batch(batch, plain_cfg, torch.Generator().manual_seed(2))
    out_b, net_b = augment_depth_batch(batch, shadow_cfg, torch.Generator().manual_seed(2))
    assert torch.equal(out_a["image"], out_b["image"]) and torch.equal(net_a["image"], net_b["image"])
    assert "image_depth" not in net_a
    assert (net_b["image_depth"] < net_b["image"] - 1e-3).any() and (net_b["image_depth"] <= net_b["image"]).all()

    module, sample, seen = _module_seeing_inputs(batch, {"flip_prob": 0.0, "jitter_prob": 0.0, "shadow_prob": 1.0})
    with torch.no_grad():
        module.training_step(sample, 0)
    _, net = augment_depth_batch(sample, module.augment, torch.Generator().manual_seed(0))
    assert torch.equal(seen["depth"], net["image_depth"])
    assert torch.allclose(seen["pose"], sample["image"], atol=1e-6)  # no jitter, no shadow for the pose network


def _ramp_pair(B: int, fx: float = 180.0, baseline: float = 0.54) -> dict:
    """B rectified KITTI-like stereo samples at H x W whose images are linear ramps (bilinear warps of a ramp are
    exact), a level camera 1.65 m above the road, no true depth."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    ramp = torch.stack([0.1 + 0.8 * u / W, 0.1 + 0.8 * v / H, 0.5 + 0.3 * (u / W - v / H)])
    K = torch.tensor([[fx, 0.0, W / 2 - 0.5], [0.0, fx, 0.45 * H], [0.0, 0.0, 1.0]])
    T = torch.eye(4)
    T[0, 3] = -baseline
    return {"image": ramp[None].repeat(B, 1, 1, 1) * torch.linspace(0.8, 1.0, B).view(B, 1, 1, 1),
            "image_right": torch.full((B, 3, H, W), 0.5), "K": K[None].repeat(B, 1, 1),
            "T_right_left": T[None].repeat(B, 1, 1), "camera_height": torch.full((B,), 1.65)}


def test_a_pasted_object_stands_on_the_road_at_its_depth_in_both_views() -> None:
    """Each pasted object is written into ``depth`` at one Z within ``paste_depth``; warping the right image into the
    left one by that depth (the stereo loss's own reprojection) reproduces the object exactly; its lowest row is the
    road's at Z (``cy + fy h / Z``, camera h above a level road); a sample without a camera height is untouched."""
    from dfvo.training.augment import paste_objects

    B = 8
    batch = _ramp_pair(B)
    batch["camera_height"][-1] = 0.0  # a synthetic sample of a mixed batch
    cfg = DepthAugmentConfig(paste_prob=1.0, paste_max=1, paste_depth=(4.0, 12.0), paste_gain=(0.5, 0.9))
    out = paste_objects(batch, cfg, torch.Generator().manual_seed(3))
    again = paste_objects(batch, cfg, torch.Generator().manual_seed(3))
    assert all(torch.equal(out[k], again[k]) for k in ("image", "image_right", "depth"))
    assert torch.equal(out["image"][-1], batch["image"][-1]) and not bool((out["depth"][-1] > 0).any())
    # the object pixels are marked (the batch had no depth: they are where depth is written) and the image as it was
    # is kept for the distillation teacher; outside the objects the left image is untouched
    assert torch.equal(out["pasted"], out["depth"] > 0) and torch.equal(out["image_unpasted"], batch["image"])
    hints = torch.full((B, 1, H, W), 30.0)
    hinted = paste_objects({**batch, "depth_hint": hints}, cfg, torch.Generator().manual_seed(3))
    assert torch.equal(hinted["depth_hint"], torch.where(out["pasted"], 0.0, 30.0))  # the hidden scene's hints go
    assert torch.equal(torch.where(out["pasted"], 0.0, out["image"]), torch.where(out["pasted"], 0.0, batch["image"]))
    fy, cy = float(batch["K"][0, 1, 1]), float(batch["K"][0, 1, 2])
    checked = scaled = 0
    for b in range(B - 1):
        d = out["depth"][b, 0]
        on = d > 0
        assert bool(on.any()), f"sample {b}: nothing pasted"
        z = float(d[on][0])
        assert torch.all(d[on] == z) and 4.0 <= z <= 12.0
        assert not torch.equal(out["image"][b], batch["image"][b]) and not torch.equal(out["image_right"][b],
                                                                                        batch["image_right"][b])
        rows = torch.nonzero(on.any(1)).flatten()
        cols = torch.nonzero(on.any(0)).flatten()
        if len(cols) < W // 2 and len(cols) > 4:  # its texture at 0.5-2 source pixels a pixel, times the gain 0.5-0.9
            r = int(rows[len(rows) // 2])
            inside = on[r, int(cols[1]):int(cols[-2]) + 1]
            assert bool(inside.all())
            row = out["image"][b, 0, r, int(cols[1]):int(cols[-2]) + 1]
            slope = row[1:] - row[:-1]
            scaled += 1
            ratio = float(slope.mean()) / float(batch["image"][b, 0, 0, 1] - batch["image"][b, 0, 0, 0])
            assert 0.25 - 1e-3 <= ratio <= 1.8 + 1e-3, f"sample {b}: texture magnified {ratio:.2f}x the source's detail"
        bottom = cy + fy * 1.65 / z
        if bottom < H - 1:
            assert abs(int(rows.max()) - bottom) <= 1.0
        else:
            assert int(rows.max()) == H - 1
        rep = reproject(out["image_right"][b:b + 1], out["depth"][b:b + 1].clamp_min(0.1),
                        batch["T_right_left"][b:b + 1], batch["K"][b:b + 1])
        inner = on & torch.roll(on, 2, 1) & torch.roll(on, -2, 1)  # away from the object's left and right edges
        inner[:, :2] = inner[:, -2:] = False
        inner &= rep.valid[0, 0]
        if int(inner.sum()) < 20:
            continue
        err = (rep.warped[0] - out["image"][b]).abs().amax(0)[inner]
        assert float(err.max()) < 1e-4, f"sample {b}: the right view's object is off by {float(err.max()):.2e}"
        # and not by chance: the same warp with a wrong depth misses it
        wrong = reproject(out["image_right"][b:b + 1], out["depth"][b:b + 1].clamp_min(0.1) * 1.5,
                          batch["T_right_left"][b:b + 1], batch["K"][b:b + 1])
        assert float((wrong.warped[0] - out["image"][b]).abs().amax(0)[inner & wrong.valid[0, 0]].max()) > 1e-2
        checked += 1
    assert checked >= 4 and scaled >= 2


def test_pasting_is_drawn_only_when_on_and_refuses_what_it_cannot_do() -> None:
    """``paste_prob`` 0 leaves the flips and jitter of a seed as they were; a batch without real samples (no camera
    height) is left as it is; a batch without a stereo partner, an unrectified pair, a training config without
    stereo or a camera height and bad ranges are refused with what is missing."""
    from dfvo.training.augment import paste_objects

    batch = _ramp_pair(2)
    plain = augment_depth_batch(batch, DepthAugmentConfig(), torch.Generator().manual_seed(1))
    off = augment_depth_batch(batch, DepthAugmentConfig(paste_prob=0.0), torch.Generator().manual_seed(1))
    assert torch.equal(plain[1]["image"], off[1]["image"]) and "depth" not in off[0]
    on, net = augment_depth_batch(batch, DepthAugmentConfig(paste_prob=1.0, jitter_prob=0.0),
                                  torch.Generator().manual_seed(1))
    assert bool((on["depth"] > 0).any()) and torch.allclose(net["image"], on["image"])
    synthetic_only = {k: v for k, v in batch.items() if k != "camera_height"}  # a mixed batch without real samples
    kept = paste_objects(synthetic_only, DepthAugmentConfig(paste_prob=1.0), torch.Generator())
    assert torch.equal(kept["image"], batch["image"]) and "depth" not in kept
    with pytest.raises(ValueError, match="'image_right'"):
        paste_objects({k: v for k, v in batch.items() if k != "image_right"}, DepthAugmentConfig(paste_prob=1.0),
                      torch.Generator())
    turned = dict(batch)
    turned["T_right_left"] = batch["T_right_left"].clone()
    turned["T_right_left"][:, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(Exception, match="rectified"):
        paste_objects(turned, DepthAugmentConfig(paste_prob=1.0), torch.Generator())
    with pytest.raises(ValueError, match="model.augment.paste_depth"):
        DepthAugmentConfig(paste_depth=(10.0, 3.0))
    with pytest.raises(ValueError, match="model.augment.paste_max"):
        DepthAugmentConfig(paste_max=0)
    with pytest.raises(ValueError, match="model.augment.paste_prob"):
        DepthAugmentConfig(paste_prob=1.5)
    from dfvo.training.depth_module import DepthPoseModule
    for data, model in (({"kind": "synthetic", "seed": 0}, {"stereo": True}),
                        ({"kind": "kitti_raw", "seed": 0, "camera_height": None}, {"stereo": True}),
                        ({"kind": "kitti_raw", "seed": 0, "camera_height": 1.65}, {"stereo": False, "temporal": True})):
        cfg = {"model": {"name": "depth_stereo", "temporal": False, **model, "augment": {"paste_prob": 0.5}},
               "data": data}
        with pytest.raises(ValueError, match="model.augment.paste_prob=0.5 pastes objects"):
            DepthPoseModule(cfg)
    DepthPoseModule({"model": {"name": "depth_stereo", "temporal": False, "augment": {"paste_prob": 0.5}},
                     "data": {"kind": "kitti_raw", "seed": 0, "camera_height": 1.65}})


def test_pasted_textures_come_from_the_rows_asked_for() -> None:
    """With ``paste_source_rows=(0.5, 1)`` every pasted pixel's texture comes from the source images' lower half: on
    images whose green channel is 0.1 + 0.8 v / H (gain 1) it reads at least 0.5 there, and less where the whole
    height may be used."""
    from dfvo.training.augment import paste_objects

    batch = _ramp_pair(8)
    v = torch.arange(H, dtype=torch.float32)
    batch["image"][:, 1] = (0.1 + 0.8 * v / H).view(H, 1)
    for rows, low in (((0.5, 1.0), True), ((0.0, 1.0), False)):
        cfg = DepthAugmentConfig(paste_prob=1.0, paste_gain=(1.0, 1.0), paste_source_rows=rows)
        out = paste_objects(batch, cfg, torch.Generator().manual_seed(4))
        green = out["image"][:, 1][out["depth"][:, 0] > 0]
        assert green.numel() > 100
        assert (float(green.min()) >= 0.1 + 0.8 * (0.5 * (H - 1)) / H - 1e-5) == low
    with pytest.raises(ValueError, match="model.augment.paste_source_rows"):
        DepthAugmentConfig(paste_source_rows=(0.8, 0.2))
