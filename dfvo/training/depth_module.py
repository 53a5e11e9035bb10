"""Lightning module for self-supervised depth (and pose) training: ``model=depth_stereo|depth_mono|depth_mono_sc``.

Config: ``cfg.model``, a :class:`dfvo.training.config.DepthModelConfig` (``model=depth_stereo|depth_mono|
depth_mono_sc``; the fields and their defaults are documented there). Validation logs the Eigen metrics raw
(``val/abs_rel``, ..., metric depth) and median-scaled (``val/abs_rel_med``, ..., monocular models). Augmentation
(flips, colour jitter) is drawn from a generator seeded by (``data.seed``, global step, DDP rank), so resuming is
exact. ``model.init_from`` starts from the weights of a file (``.safetensors``/``.pt`` DepthNet state dict, or a depth
``.ckpt``; its pose network too when it holds one) instead of random weights (not a resume: step 0, fresh optimiser;
checkpoints record the path as ``model.initialised_from``).

Loss (per scale s = 0..3, averaged over scales): every scale's disparity is upsampled to the input
resolution (monodepth2), each source view (prev, next, stereo partner) is warped into the target, the
SSIM+L1 error takes a per-pixel minimum over views (out-of-view pixels excluded), plus
``w_smooth / 2^s`` x edge-aware smoothness of the mean-normalised disparity at scale s, plus
``w_consistency`` x the inverse-depth consistency (per-pixel minimum over the temporal views), plus
``model.w_depth_supervised`` x the log-depth L1 of that scale's depth against the batch's true ``depth``
(:func:`dfvo.losses.depth_supervision.log_depth_l1`; synthetic samples; a target <= 0 marks a pixel without
ground truth, e.g. a real sample of a mixed batch; sky clamped to ``max_depth``) when the batch has ``depth`` and
the weight is > 0 (default 0: the paper's self-supervised loss alone), plus ``model.w_depth_hints`` x the depth-hint
loss (Watson et al. 2019): ``log(1 + |D_s - H|)`` averaged over the image, counted at the pixels where the batch's
stereo-matcher depth ``H`` (``depth_hint``, 0: none) reprojects the stereo partner with a lower SSIM+L1 error than
the scale's depth ``D_s`` reaches with any source view, plus ``model.w_camera_height`` x the camera-height loss
(:func:`dfvo.losses.road_height.road_height_log_l1`): the road pixels of the tracker's road band, those on the plane
fitted to the scale-0 depth (no gradient through the fit), held at the sample's known ``camera_height`` (KITTI samples;
0: none), plus ``model.w_distill`` x the log-depth L1 of that scale's depth against a trained network's
(``model.teacher``, run in inference mode on the sample's image before the shadows of ``augment.shadow_prob`` and the
objects of ``augment.paste_prob``, and not counted on the objects' pixels, whose depth is known): distillation, e.g.
into a narrower network (``model.width_multiplier``), or holding a network's scene while pasted objects teach it.
"""

from __future__ import annotations

import logging
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf

from dfvo.eval.depth_metrics import DEPTH_METRIC_NAMES, compute_depth_metrics
from dfvo.geometry.two_view import normalise_points
from dfvo.io.checkpoint import find_checkpoint, load_weights, read_state_dict
from dfvo.losses.depth_consistency import depth_consistency_loss, inverse_depth_difference
from dfvo.losses.depth_supervision import log_depth_l1
from dfvo.losses.photometric import INVALID_ERROR, min_over_views, ssim_l1_error, ssim_moments
from dfvo.losses.reprojection import reproject, source_rays
from dfvo.losses.road_height import road_height_log_l1
from dfvo.losses.smoothness import edge_aware_smoothness
from dfvo.models.depth_net import SCALES, DepthNet, disp_to_depth, network_width
from dfvo.models.pose_net import PoseNet
from dfvo.tracking.config import RoadPlaneConfig
from dfvo.tracking.ground_plane import fit_road_plane, road_grid
from dfvo.training.augment import augment_depth_batch
from dfvo.training.config import DepthModelConfig, typed
from dfvo.training.hparams import recorded_config
from dfvo.training.optimizer import adam
from dfvo.training.precision import float32_losses

MIN_SCALE_PIXELS = 100  # hinted pixels an image needs before the teacher's scale is fitted to them


def teacher_scaled_to_hints(teacher_depth: torch.Tensor, hints: torch.Tensor) -> torch.Tensor:
    """``teacher_depth`` (B,1,H,W, metres; <= 0: no target) of each image times the median of ``hints`` (B,1,H,W,
    the stereo matcher's depth; <= 0: none) ÷ ``teacher_depth`` over the pixels where both are > 0; an image with
    fewer than :data:`MIN_SCALE_PIXELS` such pixels is left as it is (``model.distill_scale_from_hints``)."""
    both = (teacher_depth > 0) & (hints > 0)
    ratio = torch.where(both, hints / teacher_depth.clamp_min(1e-6), torch.nan).flatten(1)
    scale = ratio.nanmedian(1).values
    scale = torch.where(both.flatten(1).sum(1) >= MIN_SCALE_PIXELS, scale, torch.ones_like(scale))
    return teacher_depth * scale.view(-1, 1, 1, 1)


class DepthPoseModule(L.LightningModule):
    """Train :class:`DepthNet` (and :class:`PoseNet` when temporal views are used). Task ``"depth"``.

    ``DepthPoseModule.load_from_checkpoint(path)`` rebuilds the module from the config stored in the checkpoint.
    Batches use the keys of :mod:`dfvo.data`: ``image``, ``K`` and, as configured, ``image_prev``,
    ``image_next`` (temporal), ``image_right`` + ``T_right_left`` (stereo); validation batches add ``depth``.

    Args:
        cfg: the training config (its ``model`` node is a :class:`~dfvo.training.config.DepthModelConfig`;
            ``data.seed`` seeds the augmentation), a DictConfig or the plain dict stored in a checkpoint.
    """

    def __init__(self, cfg: DictConfig | dict, **_: Any) -> None:
        super().__init__()
        cfg = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)  # dict: from load_from_checkpoint
        m: DepthModelConfig = typed(cfg.model, DepthModelConfig, "model")
        self.model_cfg = m
        self.model_type = f"{m.task}:{m.name}"
        self.stereo, self.temporal = m.stereo, m.temporal
        self.alpha, self.w_smooth, self.w_consistency = m.alpha, m.w_smooth, m.w_consistency
        self.automask = m.automask
        self.w_depth_supervised = m.w_depth_supervised
        self.w_depth_hints = m.w_depth_hints
        self.w_camera_height = m.w_camera_height
        self.min_depth, self.max_depth = m.min_depth, m.max_depth
        self.lr, self.lr_drop_fraction = m.lr, m.lr_drop_fraction
        self.log_images_every = m.log_images_every
        self.depth_net = DepthNet(self.min_depth, self.max_depth, m.init_depth, width=m.width_multiplier)
        self.w_distill = m.w_distill
        # the teacher, loaded when training first needs it (a module rebuilt from a checkpoint for evaluation does
        # not), in a tuple: not a submodule, so neither the checkpoints nor the optimiser hold it
        self._teacher: tuple[DepthNet, ...] = ()
        self.pose_net = PoseNet() if self.temporal else None
        self.augment = m.augment
        self.augment_seed = int(cfg.data.seed) if "data" in cfg else 0
        # a batch of synthetic samples alone has no hints (a mixed batch has 0, none, on its worlds' samples)
        self.hints_on_real_samples_only = "data" in cfg and cfg.data.get("kind") == "kitti_raw_synthetic"
        real = "data" in cfg and cfg.data.get("kind") in ("kitti_raw", "kitti_raw_synthetic")
        for setting, on in ((f"model.w_depth_hints={self.w_depth_hints}", self.w_depth_hints > 0),
                            ("model.distill_scale_from_hints=true", m.distill_scale_from_hints)):
            if on and real and not cfg.data.get("depth_hints", False):
                raise ValueError(f"{setting} needs the stereo matcher's hints: set data.depth_hints=true "
                                 f"(data={cfg.data.get('kind')})")
        if self.augment is not None and self.augment.paste_prob > 0 and "data" in cfg:
            height = cfg.data.get("camera_height")
            if not self.stereo or height is None:
                raise ValueError(f"model.augment.paste_prob={self.augment.paste_prob} pastes objects into real stereo "
                                 f"pairs standing on the road: it needs model.stereo=true (got {self.stereo}) and "
                                 f"data with a camera height (data=kitti_raw or kitti_raw_synthetic with "
                                 f"data.camera_height; got data={cfg.data.get('kind')}, camera_height={height})")
        # the steps and whole epochs trained before this run when it continues another from its weights
        # (continue_from, dfvo.training.continuation): the rate schedule and the exports count the whole run
        self.steps_before, self.epochs_before = 0, 0
        if m.init_from:
            self._init_weights_from(str(m.init_from))
        self.save_hyperparameters({"cfg": recorded_config(cfg)})

    def export_network(self) -> tuple[torch.nn.Module, dict[str, str]]:
        """The network inference loads (DepthNet; the pose network stays in the training checkpoint) and the
        metadata describing it (see :func:`dfvo.training.export.export_weights`)."""
        return self.depth_net, {"task": "depth", "min_depth": str(self.min_depth), "max_depth": str(self.max_depth),
                                "width_multiplier": repr(self.depth_net.width)}

    def teacher(self) -> DepthNet:
        """The distillation teacher of ``model.teacher`` (loaded on the first call): a DepthNet of the width and depth
        range its file records, in inference mode without gradients."""
        if not self._teacher:
            self._teacher = (self._load_teacher(str(self.model_cfg.teacher)),)
        return self._teacher[0]

    def _load_teacher(self, path: str) -> DepthNet:
        path = str(find_checkpoint(path, "model.teacher"))
        state, meta = read_state_dict(path, "depth network DepthNet", "model.teacher")
        teacher = DepthNet(float(meta.get("min_depth", self.min_depth)), float(meta.get("max_depth", self.max_depth)),
                           width=network_width(meta, "model.teacher", state))
        load_weights(teacher, path, "depth network DepthNet", "model.teacher", task="depth", contents=(state, meta))
        return teacher.eval().requires_grad_(False)

    def _init_weights_from(self, path: str) -> None:
        """Load DepthNet (required) and PoseNet (when the file holds one: keys under ``pose_net.``) from ``path`` (a
        relative path that does not exist is looked up in the installed package, as for flow: ``checkpoints/...``)."""
        path = str(find_checkpoint(path, "model.init_from"))
        load_weights(self.depth_net, path, "depth network DepthNet", "model.init_from", task="depth")
        if self.pose_net is None:
            return
        state, _ = read_state_dict(path, "depth network DepthNet", "model.init_from")
        if not any(k.startswith("pose_net.") for k in state):
            logging.getLogger("dfvo.training").info("model.init_from=%s holds no PoseNet: the pose network starts "
                                                    "from random weights", path)
            return
        load_weights(self.pose_net, path, "pose network PoseNet", "model.init_from", task="depth")

    def train(self, mode: bool = True) -> DepthPoseModule:
        """The train/eval switch; with ``model.freeze_bn`` the batch-norm layers stay in inference mode."""
        super().train(mode)
        if mode:
            self._freeze_batch_norm()
        return self

    def on_train_start(self) -> None:
        # Lightning starts fitting without calling train() (a new module is in training mode) and restores each
        # submodule's own mode after validation, so the batch-norm layers are set once here
        self._freeze_batch_norm()

    def _freeze_batch_norm(self) -> None:
        if self.model_cfg.freeze_bn:
            for module in self.modules():
                if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                    module.eval()

    # ---------------------------------------------------------------- forward
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """Depth (B,1,H,W) of ``image`` (B,3,H,W) at full resolution."""
        return disp_to_depth(self.depth_net(image)[0], self.min_depth, self.max_depth)

    def _sources(self, batch: dict[str, torch.Tensor], net_inputs: dict[str, torch.Tensor] | None = None
                 ) -> list[tuple[str, torch.Tensor, torch.Tensor]]:
        """(name, source image, T_source_target) for every source view; the pose network sees ``net_inputs``
        (jittered images) when given, the warps use the batch's images."""
        def need(key: str, why: str) -> torch.Tensor:
            if key not in batch:
                raise KeyError(f"DepthPoseModule ({self.model_type}): batch lacks {key!r} needed for {why}; "
                               f"got keys {sorted(batch)} (check data= and model.stereo/temporal)")
            return batch[key]
        image = need("image", "the target view")
        net = net_inputs or {}
        out = []
        if self.temporal:
            prev, nxt = need("image_prev", "temporal views"), need("image_next", "temporal views")
            n_prev, n_img, n_next = net.get("image_prev", prev), net.get("image", image), net.get("image_next", nxt)
            # the pose net sees frames in temporal order: PoseNet(a, b) = T_b_a
            T_cur_prev = self.pose_net(n_prev, n_img)
            out.append(("prev", prev, torch.linalg.inv(T_cur_prev)))
            out.append(("next", nxt, self.pose_net(n_img, n_next)))
        if self.stereo:
            out.append(("stereo", need("image_right", "stereo"), need("T_right_left", "stereo").float()))
        return out

    def _losses(self, batch: dict[str, torch.Tensor], net_inputs: dict[str, torch.Tensor] | None = None
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict]:
        image = batch["image"]
        B = image.shape[0]
        net = net_inputs or {}
        all_hints = batch.get("depth_hint")  # every row's, for the teacher's scale (distill_scale_from_hints)
        batch = self._hints_from_row(batch)
        sources = self._sources(batch, net)
        temporal = [s for s in sources if s[0] != "stereo"]
        # the depth network's input: with shadows cast (augment.shadow_prob) when drawn, else the jittered image
        depth_input = net.get("image_depth", net.get("image", image))
        teacher_depth = None
        if self.w_distill > 0:
            with torch.no_grad():
                # the scene as it was (without pasted objects) and without shadows; no teaching on pasted objects,
                # whose depth is known (augment.paste_prob)
                view = net.get("image_unpasted", net.get("image", image))
                teacher_depth = self.teacher().to(image.device).depth(view).float()
                if "pasted" in batch:
                    teacher_depth = teacher_depth.masked_fill(batch["pasted"], 0.0)  # <= 0: no target
                if self.model_cfg.distill_where_no_target:  # the worlds' truth and the stereo hints teach there
                    for key in ("depth", "depth_hint"):
                        if key in batch:
                            teacher_depth = teacher_depth.masked_fill(batch[key] > 0, 0.0)
                if self.model_cfg.distill_scale_from_hints and all_hints is not None:  # (a batch of worlds has none)
                    teacher_depth = teacher_scaled_to_hints(teacher_depth, all_hints)
        if self.w_consistency > 0:
            keys = {"prev": "image_prev", "next": "image_next"}
            views = [depth_input] + [net.get(keys[s[0]], s[1]) for s in temporal]
            disps_all = self.depth_net(torch.cat(views, 0))
            disps = {s: d[:B] for s, d in disps_all.items()}
        else:
            disps = self.depth_net(depth_input)
        with float32_losses(image.device):  # the networks may run under bf16 autocast; the losses never do
            return self._losses_from(batch, sources, disps, disps_all if self.w_consistency > 0 else None,
                                     teacher_depth)

    def _hints_from_row(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The batch with its ``depth_hint`` (B,1,H,W) zeroed (no hint) above ``model.depth_hints_from_row`` of the
        height; the batch itself when there are no hints or the setting is 0."""
        start = round(self.model_cfg.depth_hints_from_row * batch["image"].shape[-2])
        if "depth_hint" not in batch or start == 0:
            return batch
        hint = batch["depth_hint"].clone()
        hint[..., :start, :] = 0.0
        return {**batch, "depth_hint": hint}

    def _losses_from(self, batch: dict[str, torch.Tensor], sources: list[tuple[str, torch.Tensor, torch.Tensor]],
                     disps: dict[int, torch.Tensor], disps_all: dict[int, torch.Tensor] | None,
                     teacher_depth: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict]:
        image, K = batch["image"], batch["K"].float()
        B, _, H, W = image.shape
        sources = [(name, src, T.float()) for name, src, T in sources]
        disps = {s: d.float() for s, d in disps.items()}
        # the source views in one batch of n*B (view-major): one reprojection and one SSIM per scale for all of them
        n = len(sources)
        srcs = torch.cat([src for _, src, _ in sources])
        T_all, K_all, image_all = torch.cat([T for _, _, T in sources]), K.repeat(n, 1, 1), image.repeat(n, 1, 1, 1)
        rays = source_rays(T_all, K_all, H, W)  # every view's back-projected, rotated pixel rays: one per step
        # the target's SSIM moments serve every view and scale (the same values as computing them in each call)
        target_moments = tuple(m.repeat(n, 1, 1, 1) for m in ssim_moments(image))
        identity = []
        if self.automask:
            identity = list((ssim_l1_error(image_all, srcs, self.alpha, target_moments) + 1e-5).split(B))
        hint = None
        if self.w_depth_hints > 0 and ("depth_hint" in batch or not self.hints_on_real_samples_only):
            hint = self._hint_reprojection(batch, sources)
        road = None
        if self.w_camera_height > 0 and "camera_height" in batch:
            depth0 = disp_to_depth(F.interpolate(disps[0], size=(H, W), mode="bilinear", align_corners=False),
                                   self.min_depth, self.max_depth)
            road = self._road_plane(depth0, K, batch["camera_height"].float())
        terms: dict[str, torch.Tensor] = {}
        total = image.new_zeros(())
        vis: dict[str, torch.Tensor] = {}
        for s in SCALES:
            disp_full = F.interpolate(disps[s], size=(H, W), mode="bilinear", align_corners=False)
            depth = disp_to_depth(disp_full, self.min_depth, self.max_depth)
            rep = reproject(srcs, depth.repeat(n, 1, 1, 1), T_all, K_all, rays)
            errors = [*identity, *ssim_l1_error(image_all, rep.warped, self.alpha, target_moments).split(B)]
            valids = [None] * len(identity) + list(rep.valid.split(B))
            diffs, dvalids = [], []
            for k, (name, _, _) in enumerate(sources):
                view = slice(k * B, (k + 1) * B)
                if s == 0:
                    vis[name] = rep.warped[view].detach()
                if self.w_consistency > 0 and name != "stereo":
                    d_src = disp_to_depth(disps_all[s][(k + 1) * B:(k + 2) * B].float(), self.min_depth,
                                          self.max_depth)
                    d_src = F.interpolate(d_src, size=(H, W), mode="bilinear", align_corners=False)
                    sampled = F.grid_sample(d_src, rep.grid[view], mode="bilinear", padding_mode="border",
                                            align_corners=True)
                    diffs.append(inverse_depth_difference(rep.depth_in_source[view], sampled))
                    dvalids.append(rep.valid[view])
            best, mask = min_over_views(errors, valids)
            photo = (best * mask).sum() / mask.sum().clamp_min(1)
            small = F.interpolate(image, size=disps[s].shape[-2:], mode="bilinear", align_corners=False)
            smooth = edge_aware_smoothness(disps[s], small)
            loss_s = photo + self.w_smooth / (2 ** s) * smooth
            terms[f"photometric_s{s}"] = photo.detach()
            terms[f"smoothness_s{s}"] = smooth.detach()
            if diffs:
                cons = depth_consistency_loss(diffs, dvalids)
                loss_s = loss_s + self.w_consistency * cons
                terms[f"consistency_s{s}"] = cons.detach()
            if hint is not None:
                hint_depth, hint_error = hint
                own = torch.stack([torch.where(v, e, torch.full_like(e, INVALID_ERROR))
                                   for e, v in zip(errors[len(identity):], valids[len(identity):])]).amin(0)
                use = (hint_error < own).float()
                hint_loss = (torch.log1p((depth - hint_depth).abs()) * use).mean()
                loss_s = loss_s + self.w_depth_hints * hint_loss
                terms[f"depth_hints_s{s}"] = hint_loss.detach()
                terms[f"depth_hints_used_s{s}"] = use.mean().detach()
            if self.w_depth_supervised > 0 and "depth" in batch:
                sup, _ = log_depth_l1(depth, batch["depth"], self.max_depth)
                loss_s = loss_s + self.w_depth_supervised * sup
                terms[f"depth_supervised_s{s}"] = sup.detach()
            if teacher_depth is not None:
                distill, _ = log_depth_l1(depth, teacher_depth, self.max_depth)
                loss_s = loss_s + self.w_distill * distill
                terms[f"distill_s{s}"] = distill.detach()
            if road is not None:
                normal, on_road = road
                height_loss, _ = road_height_log_l1(depth, K, normal, on_road, batch["camera_height"].float())
                loss_s = loss_s + self.w_camera_height * height_loss
                terms[f"camera_height_s{s}"] = height_loss.detach()
                if s == 0:
                    terms["road_pixels"] = on_road.float().sum().detach() / B
            terms[f"loss_s{s}"] = loss_s.detach()
            total = total + loss_s / len(SCALES)
        vis["disp"] = disps[0].detach()
        return total, terms, vis

    @torch.no_grad()
    def _road_plane(self, depth: torch.Tensor, K: torch.Tensor, camera_height: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The road plane of the network's own depth (B,1,H,W) in the tracker's road band (every pixel of it;
        ``tracker.road_plane`` defaults): its normal (B,3) and the pixels on it (B,1,H,W) bool, none for a sample
        without a ``camera_height`` (> 0) or whose fit fails. The RANSAC draws are seeded by the global step and the
        sample, so a resumed run draws the same."""
        rp = RoadPlaneConfig()
        B, _, H, W = depth.shape
        px = road_grid(H, W, rp.min_row_fraction, rp.max_row_fraction, rp.max_col_offset_fraction, 1).to(depth.device)
        u, v = px[:, 0].long(), px[:, 1].long()
        z = depth[:, 0, v, u].to(torch.float64)  # (B,M)
        rays = normalise_points(px[None].expand(B, -1, -1), K.to(torch.float64))
        X = torch.cat([rays, torch.ones_like(rays[..., :1])], -1) * z[..., None]
        seed = int(self.global_step) * 1009
        plane = fit_road_plane(X, (z > 0) & (z < self.max_depth) & (camera_height > 0)[:, None],
                               threshold=rp.threshold, max_tilt_deg=rp.max_tilt_deg, min_inliers=rp.min_inliers,
                               trials=rp.trials, quantile=rp.quantile,
                               generators=[torch.Generator().manual_seed(seed + b) for b in range(B)])
        on_road = torch.zeros_like(depth, dtype=torch.bool)
        on_road[:, 0, v, u] = plane.inliers
        return plane.normal.to(depth.dtype), on_road

    @torch.no_grad()
    def _hint_reprojection(self, batch: dict[str, torch.Tensor], sources: list[tuple[str, torch.Tensor, torch.Tensor]]
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        """The batch's depth hints (B,1,H,W) and the photometric error (B,1,H,W) of the stereo partner reprojected
        with them (+inf where there is no hint, it is beyond ``max_depth`` or it leaves the image)."""
        if "depth_hint" not in batch:
            raise KeyError("model.w_depth_hints > 0: the batch has no 'depth_hint'; use data=kitti_raw (or "
                           "kitti_raw_synthetic) with data.depth_hints=true")
        name, src, T = next(x for x in sources if x[0] == "stereo")
        hint = batch["depth_hint"].float()
        rep = reproject(src, hint.clamp_min(self.min_depth), T, batch["K"].float())
        error = ssim_l1_error(batch["image"], rep.warped, self.alpha)
        ok = rep.valid & (hint > 0) & (hint <= self.max_depth)
        return hint, torch.where(ok, error, torch.full_like(error, float("inf")))

    # ---------------------------------------------------------------- steps
    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        net_inputs = None
        if self.augment is not None:
            # one stream per (data seed, step, DDP rank): resumed runs draw the same, ranks draw differently
            seed = (self.augment_seed * 1_000_003 + int(self.global_step)) * 1009 + int(self.global_rank)
            g = torch.Generator().manual_seed(seed)
            batch, net_inputs = augment_depth_batch(batch, self.augment, g)
        loss, terms, vis = self._losses(batch, net_inputs)
        bs = batch["image"].shape[0]
        self.log("train/loss", loss.detach(), prog_bar=True, batch_size=bs)
        for name, value in terms.items():
            self.log(f"train/{name}", value, batch_size=bs)
        if self.log_images_every > 0 and self.global_step % self.log_images_every == 0:
            self._log_images(batch, vis, "train")
        return loss

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        bs = batch["image"].shape[0]
        depth = self(batch["image"])
        if "depth" in batch:
            metrics = compute_depth_metrics(depth, batch["depth"], max_depth=80.0, median_scaling=False)
            scaled = compute_depth_metrics(depth, batch["depth"], max_depth=80.0, median_scaling=True)
            for k in DEPTH_METRIC_NAMES:
                self.log(f"val/{k}", metrics[k], batch_size=bs, sync_dist=True, prog_bar=k == "abs_rel")
                self.log(f"val/{k}_med", scaled[k], batch_size=bs, sync_dist=True)
        if batch_idx == 0:
            self._log_images(batch, {"disp": self.depth_net(batch["image"])[0]}, "val")

    def _log_images(self, batch: dict[str, torch.Tensor], vis: dict[str, torch.Tensor], stage: str) -> None:
        writer = getattr(self.logger, "experiment", None) if self.logger is not None else None
        if writer is None or not hasattr(writer, "add_image"):
            return
        writer.add_image(f"{stage}/image", batch["image"][0].clamp(0, 1), self.global_step)
        disp = vis["disp"][0]
        writer.add_image(f"{stage}/disparity", (disp / disp.max().clamp_min(1e-6)).clamp(0, 1), self.global_step)
        for name in ("prev", "next", "stereo"):
            if name in vis:
                writer.add_image(f"{stage}/warped_{name}", vis[name][0].clamp(0, 1), self.global_step)

    def configure_optimizers(self) -> dict[str, Any]:
        params = list(self.depth_net.parameters()) + (list(self.pose_net.parameters()) if self.pose_net else [])
        optimizer = adam(params, self.lr, self.device,
                         clipped=self._trainer is not None and self._trainer.gradient_clip_val is not None)
        total = max(int(self.trainer.estimated_stepping_batches), 1) if self._trainer is not None else 1
        # the whole run's step at which the rate drops (a continued run's steps follow self.steps_before others)
        before = self.steps_before
        drop_at = int(self.lr_drop_fraction * (total + before))
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0 if step + before < drop_at else 0.1)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
