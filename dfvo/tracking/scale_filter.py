"""Fusion of scale observations, per frame or over time (a Kalman filter over log scale).

State: ``x`` = log of the current pair's translation length (metres) and ``b`` = log of the depth network's scale
bias (its scale observations are ``exp(x + b)``). Observations per frame:

    - ``cnn``: the scale from CNN depth (``log s = x + b + noise``, std ``cnn_log_std``);
    - ``height``: the camera-height scale from the triangulated road plane (``log s = x + noise``, std
      ``height_log_std``); it makes ``b`` observable;
    - ``road_bias``: the depth network's own road plane height over the true camera height (``log = b + noise``, std
      ``height_log_std``): a direct observation of the network's scale factor near the road;
    - ``homography``: the photometric road scale, the camera height over the road's distance in the unit of the
      E-tracker's translation found by aligning the road between the images (:mod:`dfvo.tracking.road_scale`;
      ``log s = x + noise``, its own std): a length observation that uses neither the flow nor the network's metric
      scale;
    - ``temporal``: the three-frame relative scale times the previous pair's length (a prediction of ``x`` with its
      own standard error); without it the prediction is the previous length (speed random walk ``motion_log_std``).

With ``temporal`` off the filter has no memory: each frame is the inverse-variance fusion of its own observations
(``b`` starts from its prior every frame). ``b`` is estimated only when the camera height is given (else it stays 0:
the network's bias cannot be told from the true scale). Absolute observations whose innovation exceeds
``gate_sigma`` standard deviations are rejected once the filter has converged. Everything is plain Python floats:
deterministic and identical in ``step`` and ``run``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from dfvo.tracking.config import ScaleFilterConfig

__all__ = ["ScaleEstimate", "FilterState", "ScaleFilter"]

UNKNOWN_VAR = 1e6  # variance of log scale before any observation


@dataclass(frozen=True)
class FilterState:
    """Mean ``(x, b)`` and covariance ``[[pxx, pxb], [pxb, pbb]]`` of (log scale, log CNN bias)."""

    x: float = 0.0
    b: float = 0.0
    pxx: float = UNKNOWN_VAR
    pxb: float = 0.0
    pbb: float = 0.0

    @property
    def known(self) -> bool:
        """The scale has been observed (its variance is finite and small)."""
        return self.pxx < 1.0


@dataclass
class ScaleEstimate:
    """One frame's fused scale: ``scale`` (None when nothing was observed and there is no prediction), ``source``
    (``+``-joined names of the observations used, or ``prediction``), ``rejected`` (observations gated out),
    ``predicted`` (the prior's scale, None before the first observation), ``bias`` (exp(b): the CNN's scale factor
    as estimated), ``state`` (the posterior, committed by :meth:`ScaleFilter.commit`)."""

    scale: float | None
    source: str
    predicted: float | None
    bias: float
    state: FilterState
    rejected: list[str] = field(default_factory=list)
    all_rejected: bool = False


class ScaleFilter:
    """Scale fusion (see the module docstring).

    Args:
        temporal: keep the state from frame to frame (else per-frame fusion).
        estimate_bias: track the CNN bias ``b`` (meaningful with the camera-height observation and ``temporal``).
        cnn_log_std, height_log_std: per-frame standard deviations of log scale of the two absolute sources.
        motion_log_std: per-frame random walk of log scale without a temporal observation.
        temporal_log_std: floor of the temporal observation's standard error; relative_process_std: added per frame.
        bias_prior_log_std, bias_log_std: prior std of ``b`` and its per-frame random walk.
        gate_sigma: innovation gate of absolute observations (standard deviations).
        min_length: a frame that moved less (m) makes the filter forget the scale (a stop: no relative scale).
        max_rejections: after this many frames in a row whose absolute observations were all gated out, the
            filter forgets the scale and restarts from the observations (a wrong prediction cannot lock it).
        warmup_frames: no observation is gated out before this many frames have been fused since the scale was
            last unknown (robust start: the first observation only starts the average).
    """

    def __init__(self, temporal: bool, estimate_bias: bool, cnn_log_std: float, height_log_std: float,
                 motion_log_std: float, temporal_log_std: float, relative_process_std: float,
                 bias_prior_log_std: float, bias_log_std: float, gate_sigma: float,
                 min_length: float = ScaleFilterConfig.min_length,
                 max_rejections: int = ScaleFilterConfig.max_rejections,
                 warmup_frames: int = ScaleFilterConfig.warmup_frames) -> None:
        self.temporal, self.estimate_bias = bool(temporal), bool(estimate_bias)
        self.cnn_var, self.height_var = cnn_log_std ** 2, height_log_std ** 2
        self.motion_var, self.temporal_var = motion_log_std ** 2, temporal_log_std ** 2
        self.rel_var = relative_process_std ** 2
        self.bias_prior_var, self.bias_var = bias_prior_log_std ** 2, bias_log_std ** 2
        self.gate_sigma = float(gate_sigma)
        self.min_length, self.max_rejections = float(min_length), int(max_rejections)
        self.height_log_std, self.warmup_frames = float(height_log_std), int(warmup_frames)
        self.rejected_frames = 0
        self.observed_frames = 0
        self.reset()

    @classmethod
    def from_config(cls, cfg: ScaleFilterConfig, temporal: bool, height_log_std: float) -> ScaleFilter:
        """The filter of ``tracker.scale_filter`` settings ``cfg``, the bias untracked until
        :meth:`start_bias_estimate` (``height_log_std``: the road observations' noise,
        ``tracker.road_plane.log_std``)."""
        return cls(temporal=temporal, estimate_bias=False, cnn_log_std=cfg.cnn_log_std, height_log_std=height_log_std,
                   motion_log_std=cfg.motion_log_std, temporal_log_std=cfg.temporal_log_std,
                   relative_process_std=cfg.relative_process_std, bias_prior_log_std=cfg.bias_prior_log_std,
                   bias_log_std=cfg.bias_log_std, gate_sigma=cfg.gate_sigma, min_length=cfg.min_length,
                   max_rejections=cfg.max_rejections, warmup_frames=cfg.warmup_frames)

    def reset(self, bias_from: FilterState | None = None) -> None:
        """Forget the scale (the next frame starts from its own observations); the CNN bias estimate is kept, or
        taken from ``bias_from`` (e.g. the state before a frame whose result is not to be learnt from)."""
        kept = bias_from if bias_from is not None else getattr(self, "state", None)
        b, pbb = (kept.b, kept.pbb) if kept is not None else \
            (0.0, self.bias_prior_var if self.estimate_bias else 0.0)
        self.state = FilterState(b=b, pbb=pbb)
        self.rejected_frames = 0
        self.observed_frames = 0

    def start_bias_estimate(self, prior: FilterState) -> FilterState:
        """From now on track the CNN bias ``b`` (something other than the network measures the metric scale: the
        road observations make it observable), starting from its prior; returns ``prior`` (this frame's, of
        :meth:`prior`, formed while the bias was untracked) in metres. No-op when it is tracked.

        Until now every length the filter kept was the network's (its CNN scales, PnP on its depth, and the relative
        scales and constant motion that carry them on): a known scale is ``x + b``, not ``x``. So the true log length
        is the kept ``x`` less an unknown ``b`` of the prior variance: its variance grows by that variance and it is
        anti-correlated with ``b``, and the first road observation moves the length and the bias together (else a
        first frame without a road observation, whose length is the network's alone, kept the network's scale in
        the lengths that followed: KITTI 06 at every third frame, 6-12 % short throughout, docs/scale.md)."""
        if self.estimate_bias:
            return prior
        self.estimate_bias = True
        if self.state is not None:
            self.state = self._in_metres(self.state)
        return self._in_metres(prior)

    def _in_metres(self, s: FilterState) -> FilterState:
        """``s``, formed while the bias was untracked (b = 0, ``pbb`` = 0), with the bias's prior: a known scale in
        the network's units becomes ``x - b``, ``b`` ~ N(0, ``bias_prior_var``)."""
        v = self.bias_prior_var
        if not s.known:  # nothing kept: only the bias is uncertain
            return replace(s, pbb=s.pbb + v)
        return replace(s, pxx=s.pxx + v, pxb=s.pxb - v, pbb=s.pbb + v)

    # ------------------------------------------------------------------------------------------ one frame
    def prior(self, temporal_scale: float | None = None, temporal_log_std: float | None = None) -> FilterState:
        """The state predicted for this frame (``temporal_scale``: this pair's length from the relative scale)."""
        s = self.state
        if not self.temporal:
            return FilterState(b=0.0, pbb=self.bias_prior_var if self.estimate_bias else 0.0)
        pbb = s.pbb + (self.bias_var if self.estimate_bias else 0.0)
        if temporal_scale is not None and temporal_scale > 0 and s.known:
            var = max(self.temporal_var, (temporal_log_std or 0.0) ** 2) + self.rel_var
            return replace(s, x=math.log(temporal_scale), pxx=s.pxx + var, pbb=pbb)
        if not s.known:
            return replace(s, pbb=pbb)
        return replace(s, pxx=s.pxx + self.motion_var, pbb=pbb)

    def _update(self, s: FilterState, z: float, hx: float, hb: float, r: float,
                gate: bool = True) -> tuple[FilterState, bool]:
        """Kalman update with observation ``z = hx * x + hb * b + noise(r)``; False (unchanged) when gated out
        (``gate``: the innovation test applies)."""
        y = z - hx * s.x - hb * s.b
        px, pb = hx * s.pxx + hb * s.pxb, hx * s.pxb + hb * s.pbb  # P H^T
        S = hx * px + hb * pb + r
        if gate and (s.known or hx == 0.0) and y * y > self.gate_sigma ** 2 * S:
            return s, False
        kx, kb = px / S, pb / S
        return FilterState(x=s.x + kx * y, b=s.b + kb * y, pxx=s.pxx - kx * px, pxb=s.pxb - kx * pb,
                           pbb=s.pbb - kb * pb), True

    def estimate(self, prior: FilterState, cnn: float | None, height: float | None, road_bias: float | None = None,
                 temporal_used: bool = False, homography: float | None = None,
                 homography_log_std: float | None = None) -> ScaleEstimate:
        """Fuse this frame's observations into ``prior``: ``cnn``, ``height`` and ``homography`` (the photometric
        road scale, :mod:`dfvo.tracking.road_scale`; std of its log ``homography_log_std``) metric scales,
        ``road_bias`` the network's road height over the camera height (None or <= 0: absent). Until
        ``warmup_frames`` frames have been observed no observation is gated out (the first one is not trusted
        blindly: it only starts the average)."""
        if self.rejected_frames >= self.max_rejections:  # restart from this frame's observations
            prior = replace(prior, x=0.0, pxx=UNKNOWN_VAR, pxb=0.0)
            temporal_used = False
            self.observed_frames = 0
        s, used, rejected = prior, [], []
        if temporal_used:
            used.append("temporal")
        predicted = math.exp(prior.x) if prior.known else None
        hb = 1.0 if self.estimate_bias else 0.0
        gate = self.observed_frames >= self.warmup_frames
        h_var = (homography_log_std if homography_log_std is not None else self.height_log_std) ** 2
        observations = [(name, math.log(z), hx, hbi, r) for name, z, hx, hbi, r in (
            ("road", road_bias, 0.0, 1.0, self.height_var), ("height", height, 1.0, 0.0, self.height_var),
            ("homography", homography, 1.0, 0.0, h_var), ("cnn", cnn, 1.0, hb, self.cnn_var))
            if z is not None and z > 0 and math.isfinite(z) and (hx != 0.0 or self.estimate_bias)]
        # the absolute observations on their own (the prior's scale forgotten): when they disagree with the
        # prediction beyond the gate, the frame counts like one whose observations were all gated out, so a
        # prediction that ran away (the relative scale wrong over several frames) cannot outvote them for long
        # -- but only when they agree among themselves: two of them further apart than the gate mean that one is an
        # outlier (e.g. the road alignment reading a side street's slope in a turn), and their mean is then no
        # evidence against the prediction
        alone = replace(prior, x=0.0, pxx=UNKNOWN_VAR, pxb=0.0)
        for _, z, hx, hbi, r in observations:
            alone, _ = self._update(alone, z, hx, hbi, r, False)
        agree = self._agree(observations, prior)
        disagree = (gate and prior.known and alone.known and agree
                    and (alone.x - prior.x) ** 2 > self.gate_sigma ** 2 * (prior.pxx + alone.pxx))
        for name, z, hx, hbi, r in observations:
            s, ok = self._update(s, z, hx, hbi, r, gate)
            (used if ok else rejected).append(name)
        absolute = [u for u in used if u not in ("temporal", "road")]
        # (every observation gated out on its own still counts, even when they contradict each other: the prediction
        # is then far from all of them, which a runaway prediction does; without it the synthetic highway's run went
        # from 1.04 to 1.65 m RPE, docs/scale.md)
        all_rejected = (bool(rejected) and not absolute) or disagree
        if not s.known:
            return ScaleEstimate(None, "none", predicted, math.exp(s.b), s, rejected)
        source = "+".join(used) if absolute else ("temporal" if temporal_used else "prediction")
        return ScaleEstimate(math.exp(s.x), source, predicted, math.exp(s.b), s, rejected, all_rejected)

    def _agree(self, observations: list[tuple[str, float, float, float, float]], prior: FilterState) -> bool:
        """Every two observations of the length (``hx`` = 1; log values, the CNN's less the prior's bias ``b``)
        within ``gate_sigma`` standard deviations of each other (their variances, the CNN's plus the bias's)."""
        lengths = [(z - hbi * prior.b, r + hbi * hbi * prior.pbb) for _, z, hx, hbi, r in observations if hx != 0.0]
        return all((xi - xj) ** 2 <= self.gate_sigma ** 2 * (vi + vj)
                   for i, (xi, vi) in enumerate(lengths) for xj, vj in lengths[i + 1:])

    def commit(self, state: FilterState, all_rejected: bool = False) -> None:
        """Keep ``state`` (the chosen frame's posterior) for the next frame (no-op without memory);
        ``all_rejected``: every absolute observation of the frame was gated out."""
        if self.temporal:
            self.state = state
            self.rejected_frames = self.rejected_frames + 1 if all_rejected else 0
            self.observed_frames += 1

    def commit_length(self, length: float, log_std: float, prior: FilterState) -> None:
        """The frame used a translation of ``length`` metres not from the fused scale (PnP, constant motion): keep
        it as the state with variance ``log_std**2``; a length under ``min_length`` forgets the scale."""
        if not self.temporal:
            return
        self.rejected_frames = 0
        if length >= self.min_length:
            self.state = replace(prior, x=math.log(length), pxx=max(log_std ** 2, 1e-12), pxb=0.0)
        else:
            self.state = replace(prior, x=0.0, pxx=UNKNOWN_VAR, pxb=0.0)
            self.observed_frames = 0
