"""Lightning module for the optical flow network: supervised (synthetic world), self-supervised (video), or mixed
phases of both on a step schedule (the recipe of the shipped flow networks).

Config: ``cfg.model``, a :class:`dfvo.training.config.FlowModelConfig` (``model=flow_supervised|flow_self|flow_mix``;
the fields and their defaults are documented there). ``model.init_from`` starts from a Lightning ``.ckpt`` of a flow
model or a ``.safetensors`` / ``.pt`` state dict of the FlowNet (e.g. a run's ``weights.safetensors``, or a shipped
``checkpoints/flow.safetensors``); a file holding another model kind is refused with one line.

Batches use the sample keys of :mod:`dfvo.data`:
    supervised: ``image``, ``image_next``, ``flow_fwd``, ``flow_bwd``, ``flow_fwd_valid``, ``flow_bwd_valid``.
    self: ``image``, ``image_next`` and, when present, ``image_prev`` (the pair (prev, image) is added to the
    batch, so both temporal pairs of a snippet train the network).
    mixed (``data=flow_mix``, :mod:`dfvo.training.flow_data`): one batch per step, ``{"step", "sup", "self"}``.

Mode ``mixed``, one training step (global step t, in phase P of ``model.phases``):
    1. augmentation drawn from ``step_generator(data.seed, t, rank, stream=1)``: the ``sup`` pairs mirrored (per
       batch), greyscale (per pair) and jittered (per image), then the ``self`` pairs mirrored (per batch)
       (:mod:`dfvo.training.flow_augment`);
    2. loss = mean over the directions of the multi-scale EPE (``multiscale_epe``, scale s weighted 1/2^s, visible
       pixels) of the ``sup`` pairs + ``model.self_weight`` x the self-supervised loss of the ``self`` pairs
       (+ ``model.w_distill`` x the multi-scale EPE of the ``self`` pairs' flows against a trained network's,
       ``model.teacher``, on the same augmented images: :func:`distillation_loss`);
    3. Adam at P's rate (x ``lr_gamma`` from ``lr_drop_fraction`` of P's steps on; a step-interval LambdaLR), the
       gradient's global norm clipped at ``model.grad_clip_norm`` (``model=flow_mix``: 10).
    Validation: per held-out scenario, the forward-backward flow of the working-size images resized to the network
    size as inference resizes them (:class:`dfvo.sources.networks.NetworkFlow`), the flows resized back; logged
    ``val/epe/<scenario>`` (AEPE over visible pixels), ``val/epe_selected/<scenario>`` (AEPE at the best-N 2000
    forward-backward-consistent correspondences the tracker would use), and their means over the scenarios
    ``val/epe`` (the monitored metric) and ``val/epe_selected``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from dfvo.geometry.camera import resize_flow
from dfvo.io.checkpoint import find_checkpoint, load_weights
from dfvo.losses.flow_losses import endpoint_error, multiscale_epe, occlusion_mask, self_supervised_flow_loss
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.flow_warp import flow_magnitude
from dfvo.matching.selection import select_correspondences
from dfvo.models.flow_net import FlowNet
from dfvo.sources.networks import NetworkFlow, resize_images
from dfvo.training.config import FlowMode, FlowModelConfig, typed
from dfvo.training.flow_augment import augment_self_supervised, augment_supervised
from dfvo.training.flow_data import phase_at
from dfvo.training.hparams import recorded_config
from dfvo.training.optimizer import adam, clip_gradients, uses_grad_scaler
from dfvo.training.precision import float32_losses
from dfvo.training.sampling import step_generator
from dfvo.vis.colour import flow_to_color, scalar_to_color

SELECTED_CORRESPONDENCES = 2000  # best-N correspondences per pair in the held-out validation (the tracker's N)


def load_flow_weights(net: FlowNet, path: str | Path, setting: str = "model.init_from") -> None:
    """Fill ``net`` from a weights file or a Lightning checkpoint of a flow model (see :mod:`dfvo.io.checkpoint`;
    a relative path that does not exist is looked up in the installed package, where ``checkpoints/*.safetensors``
    live); errors are :class:`~dfvo.io.checkpoint.CheckpointError` naming ``setting``, the path and what it holds."""
    load_weights(net, find_checkpoint(path, setting), "flow network FlowNet", setting, task="flow")


def supervised_flow_loss(flows_fwd: list[torch.Tensor], flows_bwd: list[torch.Tensor], batch: dict[str, torch.Tensor]
                         ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Mean over the directions with a visible pixel of the multi-scale EPE (``multiscale_epe``) against the batch's
    ``flow_fwd``/``flow_bwd`` and their validity; terms: ``epe`` (the finest scale's EPE, mean of the directions)."""
    terms = []
    for flows, key in ((flows_fwd, "flow_fwd"), (flows_bwd, "flow_bwd")):
        valid = batch[f"{key}_valid"].bool()
        if bool(valid.any()):  # datasets with forward flow only (FlyingChairs, Sintel, KITTI) have no backward term
            terms.append(multiscale_epe(flows, batch[key], valid))
    if not terms:
        raise ValueError("FlowModule (supervised): the batch has no valid ground-truth flow pixel")
    loss = sum(t[0] for t in terms) / len(terms)
    return loss, {"epe": sum(t[1][0] for t in terms).detach() / len(terms)}


def distillation_loss(flows_fwd: list[torch.Tensor], flows_bwd: list[torch.Tensor], teacher_fwd: torch.Tensor,
                      teacher_bwd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over the two directions of the multi-scale EPE (``multiscale_epe``, every pixel) of the student's flows
    (lists of (B,2,H,W), finest first, at the input size) against the teacher's (B,2,H,W); and the finest scale's
    EPE (detached), mean of the directions. Computed in float32."""
    f = multiscale_epe([x.float() for x in flows_fwd], teacher_fwd.float())
    b = multiscale_epe([x.float() for x in flows_bwd], teacher_bwd.float())
    return 0.5 * (f[0] + b[0]), 0.5 * (f[1][0] + b[1][0]).detach()


class FlowModule(L.LightningModule):
    """Train :class:`dfvo.models.flow_net.FlowNet` (task ``"flow"`` of ``dfvo.training.runner``).

    ``FlowModule.load_from_checkpoint(path)`` rebuilds the module from the config stored in the checkpoint.

    Args:
        cfg: the training config (its ``model`` node is a :class:`~dfvo.training.config.FlowModelConfig`), a
            DictConfig or the plain dict stored in a checkpoint.
    """

    def __init__(self, cfg: DictConfig | dict, **_: Any) -> None:
        super().__init__()
        cfg = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)  # dict: from load_from_checkpoint
        m: FlowModelConfig = typed(cfg.model, FlowModelConfig, "model")
        self.model_cfg = m
        self.mode = m.mode.value
        self.lr, self.lr_milestones, self.lr_gamma = m.lr, list(m.lr_milestones), m.lr_gamma
        self.alpha, self.w_smooth = m.loss.alpha, m.loss.w_smooth
        self.w_consistency, self.occlusion = m.loss.w_consistency, m.loss.occlusion
        self.log_images_every = m.log_images_every
        self.phases, self.lr_drop_fraction, self.self_weight = list(m.phases), m.lr_drop_fraction, m.self_weight
        self.augment, self.grad_clip_norm = m.augment, m.grad_clip_norm
        data = cfg.get("data") or {}
        self.augment_seed = int(data.get("seed", 0) or 0)
        height, width = data.get("height"), data.get("width")
        self.input_size = (int(height), int(width)) if height and width else None  # mixed validation resizes to it
        self.net = FlowNet(m.variant)
        if m.init_from:
            load_flow_weights(self.net, m.init_from)
        self.w_distill = float(m.w_distill)
        # the distillation teacher, loaded when training first needs it; in a tuple so that it is no submodule (not
        # in checkpoints, the optimiser or the exported weights)
        self._teacher: tuple[FlowNet, ...] = ()
        self.save_hyperparameters({"cfg": recorded_config(cfg)})

    def teacher(self) -> FlowNet:
        """The distillation teacher of ``model.teacher`` (its variant from the file, as inference loads it), frozen
        and in evaluation mode, on the student's device."""
        if not self._teacher:
            loaded = NetworkFlow(find_checkpoint(str(self.model_cfg.teacher), "model.teacher")).model
            self._teacher = (loaded.requires_grad_(False).eval(),)
        return self._teacher[0].to(self.device)

    def export_network(self) -> tuple[torch.nn.Module, dict[str, str]]:
        """The network inference loads and the metadata describing it (see
        :func:`dfvo.training.export.export_weights`)."""
        return self.net, {"task": "flow", "variant": self.model_cfg.variant}

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Forward and backward flow (B,2,H,W) of a pair of (B,3,H,W) images."""
        return self.net.forward_backward(img1, img2)

    def _pairs(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        for key in ("image", "image_next"):
            if key not in batch:
                raise KeyError(f"FlowModule ({self.mode}): batch lacks {key!r}; got keys {sorted(batch)}")
        img1, img2 = batch["image"], batch["image_next"]
        if self.mode == "self" and "image_prev" in batch:
            img1 = torch.cat([batch["image_prev"], img1], 0)
            img2 = torch.cat([batch["image"], img2], 0)
        return img1, img2

    def _supervised(self, batch: dict[str, torch.Tensor], flows_fwd: list[torch.Tensor],
                    flows_bwd: list[torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        for key in ("flow_fwd", "flow_bwd", "flow_fwd_valid", "flow_bwd_valid"):
            if key not in batch:
                raise KeyError(f"FlowModule (supervised): batch lacks {key!r}; use data=synthetic (true flows), "
                               f"got keys {sorted(batch)}")
        return supervised_flow_loss(flows_fwd, flows_bwd, batch)

    def _self_supervised(self, img1: torch.Tensor, img2: torch.Tensor, flows_fwd: list[torch.Tensor],
                         flows_bwd: list[torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return self_supervised_flow_loss(img1, img2, flows_fwd, flows_bwd, alpha=self.alpha, w_smooth=self.w_smooth,
                                         w_consistency=self.w_consistency, occlusion=self.occlusion)

    # ---------------------------------------------------------------- mode "mixed"
    def mixed_loss(self, batch: dict[str, Any], generator: torch.Generator | None
                   ) -> tuple[torch.Tensor, dict[str, torch.Tensor], tuple[torch.Tensor, ...] | None]:
        """The loss of one step batch of ``data=flow_mix`` (see the module docstring), augmented with draws from
        ``generator`` (None or no ``model.augment``: none). Returns ``(loss, terms, view)``; ``view`` is the first
        supervised (or KITTI) pair's images and flows for TensorBoard."""
        loss = torch.zeros((), device=self.device)
        terms: dict[str, torch.Tensor] = {}
        view = None
        sup, kitti = batch.get("sup"), batch.get("self")
        if sup is not None:
            i1, i2, ff, fb, vf, vb = (sup[k] for k in ("image", "image_next", "flow_fwd", "flow_bwd",
                                                        "flow_fwd_valid", "flow_bwd_valid"))
            if self.augment is not None and generator is not None:
                i1, i2, ff, fb, vf, vb = augment_supervised(i1, i2, ff, fb, vf, vb, self.augment, generator)
            flows_f, flows_b = self.net.forward_backward(i1, i2, all_scales=True)
            with float32_losses(self.device):  # losses in fp32 in mixed-precision runs
                flows_f, flows_b = [f.float() for f in flows_f], [f.float() for f in flows_b]
                sup_loss, sup_terms = supervised_flow_loss(
                    flows_f, flows_b, {"flow_fwd": ff, "flow_bwd": fb, "flow_fwd_valid": vf, "flow_bwd_valid": vb})
            loss = loss + sup_loss
            terms.update(sup_loss=sup_loss.detach(), **sup_terms)
            view = (i1, i2, flows_f[0].detach(), flows_b[0].detach(), ff)
        if kitti is not None:
            k1, k2 = kitti["image"], kitti["image_next"]
            if self.augment is not None and generator is not None:
                k1, k2 = augment_self_supervised(k1, k2, self.augment, generator)
            kf, kb = self.net.forward_backward(k1, k2, all_scales=True)
            teacher_flows = None
            if self.w_distill > 0:
                with torch.no_grad():
                    teacher_flows = self.teacher().forward_backward(k1, k2)
            with float32_losses(self.device):
                self_loss, self_terms = self._self_supervised(k1.float(), k2.float(), [f.float() for f in kf],
                                                              [f.float() for f in kb])
                loss = loss + self.self_weight * self_loss
                terms.update(self_loss=self_loss.detach(), **{f"self_{k}": v for k, v in self_terms.items()})
                if teacher_flows is not None:
                    distill, distill_epe = distillation_loss(kf, kb, *teacher_flows)
                    loss = loss + self.w_distill * distill
                    terms.update(distill=distill.detach(), distill_epe=distill_epe)
            if view is None:
                view = (k1, k2, kf[0].float().detach(), kb[0].float().detach(), None)
        if sup is None and kitti is None:
            raise ValueError("FlowModule (mixed): the step batch holds neither 'sup' nor 'self' pairs")
        return loss, terms, view

    def _mixed_training_step(self, batch: dict[str, Any]) -> torch.Tensor:
        step = int(batch["step"])
        if step != int(self.global_step):
            raise RuntimeError(f"FlowModule (mixed): the data gave the batch of step {step} at global step "
                               f"{self.global_step}; the data position and the schedule disagree (a resume with "
                               "changed data settings?)")
        g = step_generator(self.augment_seed, step, int(self.global_rank), stream=1)
        loss, terms, view = self.mixed_loss(batch, g)
        phase, _ = phase_at(self.phases, step)
        bs = next(v for v in (batch.get("sup"), batch.get("self")) if v is not None)["image"].shape[0]
        self.log("train/loss", loss.detach(), prog_bar=True, batch_size=bs)
        for name, value in terms.items():
            self.log(f"train/{name}", value, prog_bar=name == "epe", batch_size=bs)
        self.log("train/phase", float(self.phases.index(phase)), batch_size=bs)
        if self.log_images_every > 0 and self.global_step % self.log_images_every == 0 and view is not None:
            i1, i2, f, b, true = view
            self._log_images(i1, i2, f, b, {"flow_fwd": true} if true is not None else {}, "train")
        return loss

    @torch.no_grad()
    def heldout_errors(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Endpoint errors of a held-out batch (working-size ``image``, ``image_next``, ``flow``, ``valid``) through
        the inference resizing: ``(visible, selected)``, the errors (pixels) at the visible pixels and at the visible
        pixels among the best-N forward-backward-consistent correspondences of every pair."""
        i1, i2, gt, valid = batch["image"], batch["image_next"], batch["flow"], batch["valid"].bool()
        size = self.input_size or tuple(i1.shape[-2:])
        fwd, bwd = self.net.forward_backward(resize_images(i1, size), resize_images(i2, size))
        fwd, bwd = resize_flow(fwd.float(), tuple(gt.shape[-2:])), resize_flow(bwd.float(), tuple(gt.shape[-2:]))
        err = flow_magnitude(fwd - gt)
        sel = select_correspondences(fwd, forward_backward_inconsistency(fwd, bwd), method="best_n",
                                     num=SELECTED_CORRESPONDENCES, relaxed_inconsistency=())
        selected = []
        for b in range(fwd.shape[0]):
            pix = sel.pts_i[b][sel.mask[b]].long()
            keep = valid[b, 0, pix[:, 1], pix[:, 0]]
            selected.append(err[b, 0, pix[:, 1], pix[:, 0]][keep])
        return err[valid], torch.cat(selected)

    def _mixed_validation_step(self, batch: dict[str, Any]) -> None:
        visible, selected = self.heldout_errors(batch)
        name = batch["name"]
        epe = visible.mean()
        epe_sel = selected.mean() if selected.numel() else torch.tensor(float("nan"), device=epe.device)
        for key, value in ((f"val/epe/{name}", epe), (f"val/epe_selected/{name}", epe_sel), ("val/epe", epe),
                           ("val/epe_selected", epe_sel)):
            self.log(key, value, batch_size=1, sync_dist=True, prog_bar=key == "val/epe")

    def _step(self, batch: dict[str, torch.Tensor], stage: str, batch_idx: int) -> torch.Tensor:
        img1, img2 = self._pairs(batch)
        flows_fwd, flows_bwd = self.net.forward_backward(img1, img2, all_scales=True)
        with float32_losses(self.device):  # losses in fp32 in mixed-precision runs
            flows_fwd, flows_bwd = [f.float() for f in flows_fwd], [f.float() for f in flows_bwd]
            if self.mode == "supervised":
                loss, terms = self._supervised(batch, flows_fwd, flows_bwd)
            else:
                loss, terms = self._self_supervised(img1.float(), img2.float(), flows_fwd, flows_bwd)
            if "flow_fwd" in batch and "flow_fwd_valid" in batch:
                b = batch["image"].shape[0]
                terms["epe"] = endpoint_error(flows_fwd[0][-b:], batch["flow_fwd"], batch["flow_fwd_valid"].bool())
        bs = img1.shape[0]
        self.log(f"{stage}/loss", loss.detach(), prog_bar=True, batch_size=bs, sync_dist=stage != "train")
        for name, value in terms.items():
            self.log(f"{stage}/{name}", value, prog_bar=name == "epe", batch_size=bs, sync_dist=stage != "train")
        if stage == "train" and self.log_images_every > 0 and self.global_step % self.log_images_every == 0:
            self._log_images(img1, img2, flows_fwd[0].detach(), flows_bwd[0].detach(), batch, stage)
        elif stage == "val" and batch_idx == 0:
            self._log_images(img1, img2, flows_fwd[0].detach(), flows_bwd[0].detach(), batch, stage)
        return loss

    def _log_images(self, img1: torch.Tensor, img2: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor,
                    batch: dict[str, torch.Tensor], stage: str) -> None:
        logger = self.logger
        writer = getattr(logger, "experiment", None) if logger is not None else None
        if writer is None or not hasattr(writer, "add_image"):
            return
        visible, diff = occlusion_mask(flow_fwd[:1], flow_bwd[:1])
        max_mag = None
        if "flow_fwd" in batch and self.mode != "self":
            max_mag = float(batch["flow_fwd"][:1].norm(dim=1).amax().clamp(min=1e-3))
            writer.add_image(f"{stage}/flow_fwd_true", flow_to_color(batch["flow_fwd"][:1], max_mag)[0],
                             self.global_step)
        writer.add_image(f"{stage}/image", img1[0].clamp(0, 1), self.global_step)
        writer.add_image(f"{stage}/flow_fwd", flow_to_color(flow_fwd[:1], max_mag)[0], self.global_step)
        writer.add_image(f"{stage}/flow_bwd", flow_to_color(flow_bwd[:1], max_mag)[0], self.global_step)
        writer.add_image(f"{stage}/fb_inconsistency", scalar_to_color(diff, vmax=3.0)[0], self.global_step)
        writer.add_image(f"{stage}/visible", visible[0].float(), self.global_step)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        if self.mode == FlowMode.mixed.value:
            return self._mixed_training_step(batch)
        return self._step(batch, "train", batch_idx)

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor | None:
        if self.mode == FlowMode.mixed.value:
            return self._mixed_validation_step(batch)
        return self._step(batch, "val", batch_idx)

    def configure_gradient_clipping(self, optimizer: torch.optim.Optimizer, gradient_clip_val: float | None = None,
                                    gradient_clip_algorithm: str | None = None) -> None:
        """``model.grad_clip_norm`` (global 2-norm) when set, else the trainer's ``gradient_clip_val``."""
        if self.grad_clip_norm is not None:
            gradient_clip_val, gradient_clip_algorithm = self.grad_clip_norm, "norm"
        if uses_grad_scaler(self._trainer):  # Lightning unscales first (the optimiser is not fused then)
            self.clip_gradients(optimizer, gradient_clip_val=gradient_clip_val,
                                gradient_clip_algorithm=gradient_clip_algorithm)
        elif gradient_clip_val:
            clip_gradients(self.net.parameters(), gradient_clip_val, gradient_clip_algorithm or "norm")

    def lr_at(self, step: int) -> float:
        """Mode ``mixed``: the learning rate of global ``step`` (its phase's rate, x ``lr_gamma`` from
        ``lr_drop_fraction`` of the phase's steps on)."""
        phase, start = phase_at(self.phases, step)
        dropped = step - start >= self.lr_drop_fraction * phase.steps
        return phase.lr * (self.lr_gamma if dropped else 1.0)

    def _clipped_through_scaler(self) -> bool:
        """Whether gradients are clipped through a gradient scaler (``model.grad_clip_norm`` or the trainer's
        ``gradient_clip_val`` with ``16-mixed``), which the fused Adam cannot follow (dfvo.training.optimizer)."""
        trainer = self._trainer
        clipped = self.grad_clip_norm is not None or (trainer is not None and trainer.gradient_clip_val is not None)
        return clipped and uses_grad_scaler(trainer)

    def configure_optimizers(self) -> dict[str, Any]:
        if self.mode == FlowMode.mixed.value:
            base = self.lr_at(0)
            optimizer = adam(self.net.parameters(), base, self.device, clipped=self._clipped_through_scaler())
            scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: self.lr_at(step) / base)
            return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
        optimizer = adam(self.net.parameters(), self.lr, self.device, clipped=self._clipped_through_scaler())
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=self.lr_milestones,
                                                         gamma=self.lr_gamma)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}
