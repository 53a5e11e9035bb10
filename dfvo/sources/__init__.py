"""What gives flow and depth at inference: trained networks or the synthetic world's ground truth (oracle).

Common interface (duck-typed):
    ``FlowSource(images_prev (B,3,H,W), images_cur (B,3,H,W), indices=None) -> (flow_fwd, flow_bwd)``, each
    (B,2,H,W) in pixels, prev→cur on prev's pixels and cur→prev on cur's pixels.
    ``DepthSource(images (B,3,H,W), indices=None) -> depth (B,1,H,W)`` in metres.
    ``indices`` are the frames' indices in their sequence (only the oracle needs them).

``source: auto`` (the default of ``infer.py``) uses the trained checkpoint when the file exists and the oracle
otherwise on synthetic data, so ``python infer.py`` runs on a fresh clone before the networks are shipped.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from dfvo.sources.networks import CheckpointError, NetworkDepth, NetworkFlow, load_weights
from dfvo.sources.oracle import OracleDepth, OracleFlow

log = logging.getLogger("dfvo.sources")

__all__ = ["find_checkpoint", "resolve_source", "check_sources", "CheckpointError", "NetworkDepth", "NetworkFlow",
           "OracleDepth", "OracleFlow", "build_flow_source", "build_depth_source", "load_weights"]


def find_checkpoint(path: str | Path | None) -> Path:
    """A relative checkpoint path is looked up in the working directory, then in the installed package (where the
    shipped ``checkpoints/`` live: ``checkpoints/flow.safetensors`` is ``dfvo/checkpoints/flow.safetensors``); the
    working-directory path is returned when neither exists."""
    if not path:
        raise CheckpointError("no checkpoint given: set flow.checkpoint= / depth.checkpoint= to a weights file")
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    shipped = Path(__file__).resolve().parents[1] / p
    return shipped if shipped.exists() else p


def resolve_source(cfg: Any, world: Any, what: str) -> str:
    """``source: auto`` becomes ``network`` when ``checkpoint`` exists, else ``oracle`` on synthetic data
    (logged); on real data without the checkpoint it raises a :class:`CheckpointError` naming the file."""
    kind = cfg.get("source")
    if kind != "auto":
        return kind
    ckpt = cfg.get("checkpoint")
    if ckpt and find_checkpoint(ckpt).is_file():
        return "network"
    if world is not None:
        log.info("%s=auto: %s not found, using the oracle (true %s of the synthetic world)", what, ckpt, what)
        return "oracle"
    raise CheckpointError(f"{what}=auto: {what} network checkpoint {ckpt} does not exist and this dataset has no "
                          f"ground truth for {what}=oracle; set {what}.checkpoint=PATH (a trained "
                          f"{'FlowNet' if what == 'flow' else 'DepthNet'})")


NETWORKS = {"flow": "FlowNet", "depth": "DepthNet"}
ORACLES = {"flow": OracleFlow, "depth": OracleDepth}


def check_sources(flow_cfg: Any, depth_cfg: Any, world: Any = None) -> dict[str, str]:
    """Resolve the ``flow`` and ``depth`` sources together, before either is built, and report every problem at
    once: an ``auto`` source without its checkpoint on data without ground truth, a ``network`` source whose
    checkpoint file does not exist, an ``oracle`` source on data without ground truth.

    Returns:
        ``{"flow": kind, "depth": kind}`` with ``auto`` resolved (``"oracle"`` or ``"network"``).

    Raises:
        CheckpointError: when a checkpoint is missing, naming each problem (one line per source).
        ValueError: when the only problems are oracle sources on data without ground truth.
    """
    kinds: dict[str, str] = {}
    problems: list[str] = []
    missing_checkpoint = False
    for what, cfg in (("flow", flow_cfg), ("depth", depth_cfg)):
        try:
            kinds[what] = kind = resolve_source(cfg, world, what)
            ckpt = cfg.get("checkpoint")
            if kind == "network" and not (ckpt and find_checkpoint(ckpt).is_file()):
                raise CheckpointError(f"{what}=network: {what} network checkpoint {ckpt} does not exist; set "
                                      f"{what}.checkpoint=PATH (a trained {NETWORKS[what]})")
            if kind == "oracle":
                ORACLES[what](world)  # raises when the data has no ground truth
        except CheckpointError as err:
            problems.append(str(err))
            missing_checkpoint = True
        except ValueError as err:
            problems.append(str(err))
    if problems:
        text = "\n  ".join(problems)
        if len(problems) > 1:
            text = "flow and depth sources cannot be built:\n  " + text
        raise CheckpointError(text) if missing_checkpoint else ValueError(text)
    return kinds


def build_flow_source(cfg: Any, world: Any = None, device: str = "cpu") -> OracleFlow | NetworkFlow:
    """Flow source from the ``flow`` config group (``source: oracle|network|auto``, ``checkpoint``, ``variant``,
    ``input_size``)."""
    kind = resolve_source(cfg, world, "flow")
    if kind == "oracle":
        return OracleFlow(world)
    if kind == "network":
        return NetworkFlow(find_checkpoint(cfg.get("checkpoint")), cfg.get("variant"), device=device,
                           input_size=cfg.get("input_size"))
    raise ValueError(f"flow.source={kind!r}; expected 'oracle', 'network' or 'auto' (conf/flow/*.yaml)")


def build_depth_source(cfg: Any, world: Any = None, device: str = "cpu") -> OracleDepth | NetworkDepth:
    """Depth source from the ``depth`` config group (``source: oracle|network|auto``, ``checkpoint``,
    ``depth_scale``, depth range, ``input_size``)."""
    kind = resolve_source(cfg, world, "depth")
    if kind == "oracle":
        return OracleDepth(world)
    if kind == "network":
        return NetworkDepth(find_checkpoint(cfg.get("checkpoint")), cfg.get("depth_scale", 1.0),
                            cfg.get("min_depth", 0.1), cfg.get("max_depth", 100.0), device=device,
                            input_size=cfg.get("input_size"), flip_average=bool(cfg.get("flip_average", False)))
    raise ValueError(f"depth.source={kind!r}; expected 'oracle', 'network' or 'auto' (conf/depth/*.yaml)")
