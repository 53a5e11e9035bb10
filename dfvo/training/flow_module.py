"""Lightning module for the optical flow network: supervised (synthetic world) or self-supervised (video).

Config: ``cfg.model``, a :class:`dfvo.training.config.FlowModelConfig` (``model=flow_supervised|flow_self``; the
fields and their defaults are documented there). ``model.init_from`` starts from a Lightning ``.ckpt`` of this module
or a ``.safetensors`` / ``.pt`` state dict of the FlowNet (e.g. a run's ``weights.safetensors``).

Batches use the sample keys of :mod:`dfvo.data`:
    supervised: ``image``, ``image_next``, ``flow_fwd``, ``flow_bwd``, ``flow_fwd_valid``, ``flow_bwd_valid``.
    self: ``image``, ``image_next`` and, when present, ``image_prev`` (the pair (prev, image) is added to the
    batch, so both temporal pairs of a snippet train the network).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from dfvo.io.checkpoint import load_weights
from dfvo.losses.flow_losses import endpoint_error, multiscale_epe, occlusion_mask, self_supervised_flow_loss
from dfvo.models.flow_net import FlowNet
from dfvo.training.config import FlowModelConfig, typed
from dfvo.training.hparams import recorded_config
from dfvo.vis.colour import flow_to_color, scalar_to_color


def load_flow_weights(net: FlowNet, path: str | Path, setting: str = "model.init_from") -> None:
    """Fill ``net`` from a weights file or a Lightning checkpoint of a flow model (see :mod:`dfvo.io.checkpoint`);
    errors are :class:`~dfvo.io.checkpoint.CheckpointError` naming ``setting`` and the path."""
    load_weights(net, path, "flow network FlowNet", setting)


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
        self.net = FlowNet(m.variant)
        if m.init_from:
            load_flow_weights(self.net, m.init_from)
        self.save_hyperparameters({"cfg": recorded_config(cfg)})

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
        terms = []
        for flows, key in ((flows_fwd, "flow_fwd"), (flows_bwd, "flow_bwd")):
            valid = batch[f"{key}_valid"].bool()
            if bool(valid.any()):  # datasets with forward flow only (FlyingChairs, Sintel, KITTI) have no backward term
                terms.append(multiscale_epe(flows, batch[key], valid))
        if not terms:
            raise ValueError("FlowModule (supervised): the batch has no valid ground-truth flow pixel")
        loss = sum(t[0] for t in terms) / len(terms)
        return loss, {"epe": sum(t[1][0] for t in terms).detach() / len(terms)}

    def _step(self, batch: dict[str, torch.Tensor], stage: str, batch_idx: int) -> torch.Tensor:
        img1, img2 = self._pairs(batch)
        flows_fwd, flows_bwd = self.net.forward_backward(img1, img2, all_scales=True)
        if self.mode == "supervised":
            loss, terms = self._supervised(batch, flows_fwd, flows_bwd)
        else:
            loss, terms = self_supervised_flow_loss(img1, img2, flows_fwd, flows_bwd, alpha=self.alpha,
                                                    w_smooth=self.w_smooth, w_consistency=self.w_consistency,
                                                    occlusion=self.occlusion)
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
        if "flow_fwd" in batch and self.mode == "supervised":
            max_mag = float(batch["flow_fwd"][:1].norm(dim=1).amax().clamp(min=1e-3))
            writer.add_image(f"{stage}/flow_fwd_true", flow_to_color(batch["flow_fwd"][:1], max_mag)[0],
                             self.global_step)
        writer.add_image(f"{stage}/image", img1[0].clamp(0, 1), self.global_step)
        writer.add_image(f"{stage}/flow_fwd", flow_to_color(flow_fwd[:1], max_mag)[0], self.global_step)
        writer.add_image(f"{stage}/flow_bwd", flow_to_color(flow_bwd[:1], max_mag)[0], self.global_step)
        writer.add_image(f"{stage}/fb_inconsistency", scalar_to_color(diff, vmax=3.0)[0], self.global_step)
        writer.add_image(f"{stage}/visible", visible[0].float(), self.global_step)

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        return self._step(batch, "train", batch_idx)

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        return self._step(batch, "val", batch_idx)

    def configure_optimizers(self) -> dict[str, Any]:
        optimizer = torch.optim.Adam(self.net.parameters(), lr=self.lr)
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=self.lr_milestones,
                                                         gamma=self.lr_gamma)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}
