"""The configuration a training module records in its checkpoints (``hyper_parameters["cfg"]``).

``model.init_from`` names the weights a run *started* from. Once the run has written a checkpoint those weights live
in it, so the recorded config moves the path to ``model.initialised_from`` (kept for provenance) and clears
``model.init_from``: rebuilding the module from a checkpoint (``load_from_checkpoint``, a resume) then never reads,
or needs, the original file again.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

__all__ = ["recorded_config"]


def recorded_config(cfg: DictConfig) -> dict[str, Any]:
    """``cfg`` as a plain dict of strings, numbers, lists and dicts (enums as their values, so a weights-only reader
    can open the checkpoint) with ``model.init_from`` moved to ``model.initialised_from``."""
    out = OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
    model = out.get("model") if isinstance(out, dict) else None
    if isinstance(model, dict) and model.get("init_from"):
        model["initialised_from"] = model["init_from"]
        model["init_from"] = None
    return out
