"""What gives flow and depth at inference: trained networks, the synthetic world's ground truth (oracle), or a
classical flow (OpenCV DIS) — each behind the :class:`FlowSource` / :class:`DepthSource` interfaces.

``source: auto`` (the default of ``infer.py``) uses the trained checkpoint when the file exists and the oracle
otherwise on synthetic data, so ``python infer.py`` runs on a fresh clone whatever is shipped.
"""

from __future__ import annotations

import logging
from typing import Any

from dfvo.io.checkpoint import CheckpointError, find_checkpoint, load_weights
from dfvo.sources.base import DepthSource, FlowSource
from dfvo.sources.config import DepthSourceConfig, DepthSourceKind, FlowSourceConfig, FlowSourceKind
from dfvo.sources.dis import DISFlow
from dfvo.sources.every_kth import EveryKthDepth
from dfvo.sources.networks import NetworkDepth, NetworkFlow
from dfvo.sources.oracle import OracleDepth, OracleFlow

log = logging.getLogger("dfvo.sources")

__all__ = ["FlowSource", "DepthSource", "FlowSourceConfig", "DepthSourceConfig", "resolve_source", "check_sources",
           "build_flow_source", "build_depth_source", "CheckpointError", "NetworkDepth", "NetworkFlow", "OracleDepth",
           "OracleFlow", "find_checkpoint", "load_weights"]

NETWORKS = {"flow": "FlowNet", "depth": "DepthNet"}
ORACLES = {"flow": OracleFlow, "depth": OracleDepth}


def resolve_source(cfg: Any, world: Any, what: str) -> str:
    """The source kind a ``flow``/``depth`` config selects, with ``auto`` resolved: ``network`` when the checkpoint
    exists, else ``oracle`` on synthetic data (logged); on real data without the checkpoint a
    :class:`CheckpointError` names the file."""
    kind = str(cfg.source.value if hasattr(cfg.source, "value") else cfg.source)
    if kind != "auto":
        return kind
    ckpt = cfg.checkpoint
    if ckpt and find_checkpoint(ckpt, f"{what}.checkpoint").is_file():
        return "network"
    if world is not None:
        log.info("%s=auto: %s not found, using the oracle (true %s of the synthetic world)", what, ckpt, what)
        return "oracle"
    raise CheckpointError(f"{what}=auto: {what} network checkpoint {ckpt} does not exist and this dataset has no "
                          f"ground truth for {what}=oracle; set {what}.checkpoint=PATH (a trained {NETWORKS[what]})")


def check_sources(flow_cfg: Any, depth_cfg: Any, world: Any = None) -> dict[str, str]:
    """Resolve the ``flow`` and ``depth`` sources together, before either is built, and report every problem at
    once: an ``auto`` source without its checkpoint on data without ground truth, a ``network`` source whose
    checkpoint does not exist, an ``oracle`` source on data without ground truth.

    Returns:
        ``{"flow": kind, "depth": kind}`` with ``auto`` resolved.

    Raises:
        CheckpointError: a checkpoint is missing (one line per problem).
        ValueError: the only problems are oracle sources on data without ground truth.
    """
    kinds: dict[str, str] = {}
    problems: list[str] = []
    missing_checkpoint = False
    for what, cfg in (("flow", flow_cfg), ("depth", depth_cfg)):
        try:
            kinds[what] = kind = resolve_source(cfg, world, what)
            if kind == "network" and not (cfg.checkpoint and find_checkpoint(cfg.checkpoint,
                                                                             f"{what}.checkpoint").is_file()):
                raise CheckpointError(f"{what}=network: {what} network checkpoint {cfg.checkpoint} does not exist; "
                                      f"set {what}.checkpoint=PATH (a trained {NETWORKS[what]})")
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


def build_flow_source(cfg: FlowSourceConfig, world: Any = None, device: str = "cpu") -> FlowSource:
    """The flow source a :class:`FlowSourceConfig` describes (``world``: the synthetic world for the oracle)."""
    kind = resolve_source(cfg, world, "flow")
    if kind == FlowSourceKind.oracle:
        return OracleFlow(world)
    if kind == FlowSourceKind.network:
        return NetworkFlow(find_checkpoint(cfg.checkpoint, "flow.checkpoint"), cfg.variant, device=device,
                           input_size=cfg.input_size, runtime=cfg.runtime)
    if kind == FlowSourceKind.dis:
        return DISFlow(preset=cfg.preset, device=device)
    raise ValueError(f"flow.source={kind!r}; expected one of {[k.value for k in FlowSourceKind]}")


def build_depth_source(cfg: DepthSourceConfig, world: Any = None, device: str = "cpu") -> DepthSource:
    """The depth source a :class:`DepthSourceConfig` describes (``world``: the synthetic world for the oracle)."""
    kind = resolve_source(cfg, world, "depth")
    if kind == DepthSourceKind.oracle:
        source: DepthSource = OracleDepth(world)
    elif kind == DepthSourceKind.network:
        source = NetworkDepth(find_checkpoint(cfg.checkpoint, "depth.checkpoint"), cfg.depth_scale, cfg.min_depth,
                              cfg.max_depth, device=device, input_size=cfg.input_size, flip_average=cfg.flip_average,
                              runtime=cfg.runtime)
    else:
        raise ValueError(f"depth.source={kind!r}; expected one of {[k.value for k in DepthSourceKind]}")
    return source if int(cfg.every) == 1 else EveryKthDepth(source, int(cfg.every))
