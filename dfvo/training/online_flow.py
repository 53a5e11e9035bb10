"""Online self-supervised finetuning of the flow network on the running sequence (paper: "Self-Flow (Online)").

The tracker calls :meth:`OnlineFlowFinetuner.step` once per new frame pair before (or after) estimating the
flow it uses; during the first ``max_frames`` pairs the network takes one Adam step (lr 1e-5) on the
self-supervised flow loss of that pair (photometric SSIM+L1 alpha=0.85, lambda_fs=0.1 edge-aware smoothness,
lambda_fc=5e-3 forward-backward consistency, occlusion-masked, each scale's term divided by 2**scale).
After that the network is frozen again (``eval`` mode) and ``step`` returns None.

Convention:
    Images (1,3,H,W) or (B,3,H,W) float in [0,1]; ``img_prev`` is frame t-1 and ``img_cur`` frame t.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.losses.flow_losses import self_supervised_flow_loss
from dfvo.models.flow_net import FlowNet


@dataclass
class OnlineFlowConfig:
    """Online finetuning settings (official defaults)."""

    lr: float = 1e-5
    max_frames: int = 200
    alpha: float = 0.85
    w_smooth: float = 0.1
    w_consistency: float = 5e-3
    occlusion: bool = True


class OnlineFlowFinetuner:
    """Adapt a :class:`FlowNet` on the first ``max_frames`` pairs of a sequence, one Adam step per pair.

    Args:
        model: the flow network (its parameters are updated in place).
        cfg: settings; defaults are the paper's (Adam, lr 1e-5, first 200 frames).
    """

    def __init__(self, model: FlowNet, cfg: OnlineFlowConfig | None = None) -> None:
        self.model = model
        self.cfg = cfg or OnlineFlowConfig()
        KORNIA_CHECK(self.cfg.max_frames >= 0, f"OnlineFlowConfig.max_frames must be >= 0, got {self.cfg.max_frames}")
        self.optimizer = torch.optim.Adam(model.parameters(), lr=self.cfg.lr)
        self.num_steps = 0

    @property
    def active(self) -> bool:
        """Whether the next call to :meth:`step` will update the network."""
        return self.num_steps < self.cfg.max_frames

    def reset(self) -> None:
        """Start a new sequence: the step counter and Adam's moments are cleared (weights are kept)."""
        self.num_steps = 0
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.cfg.lr)

    def step(self, img_prev: torch.Tensor, img_cur: torch.Tensor) -> float | None:
        """One finetuning step on the pair (prev, cur).

        Args:
            img_prev: (B,3,H,W) frame t-1 in [0,1].
            img_cur: (B,3,H,W) frame t in [0,1].

        Returns:
            The loss of this pair before the update (float), or None once ``max_frames`` pairs were used.
            The model is left in ``eval`` mode either way.
        """
        KORNIA_CHECK_SHAPE(img_prev, ["B", "3", "H", "W"])
        KORNIA_CHECK_SHAPE(img_cur, ["B", "3", "H", "W"])
        if not self.active:
            self.model.eval()
            return None
        self.model.train()
        with torch.enable_grad():
            flows_fwd, flows_bwd = self.model.forward_backward(img_prev, img_cur, all_scales=True)
            loss, _ = self_supervised_flow_loss(img_prev, img_cur, flows_fwd, flows_bwd, alpha=self.cfg.alpha,
                                                w_smooth=self.cfg.w_smooth, w_consistency=self.cfg.w_consistency,
                                                occlusion=self.cfg.occlusion)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
        self.num_steps += 1
        self.model.eval()
        return float(loss.detach())
