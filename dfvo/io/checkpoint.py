"""Network checkpoints: the one place that finds, reads, checks and writes weight files.

Files read:
    - ``.safetensors`` (the shipped, weights-only format; string metadata such as ``task``, ``variant``, the
      ``height``/``width`` the network was trained at),
    - ``.pt`` / ``.pth`` / ``.ckpt`` read with ``torch.load(weights_only=True)`` (tensors and plain containers, no
      pickled code): a state dict, or a Lightning checkpoint whose ``state_dict`` holds the network under a prefix
      (``net.``, ``depth_net.``, ``pose_net.``, ...); the prefix that matches the expected network is stripped.
    - Resumable training checkpoints (:func:`load_training_checkpoint`) carry the model identity
      ``MODEL_IDENTITY_KEY`` (``"task:name"``, e.g. ``"depth:depth_stereo"``) so a run refuses to resume another
      model's state.

Weights that are not finite (NaN, inf: a file whose data bytes were damaged while its header still reads) are
refused at load time, naming the file and a tensor.

Every failure raises :class:`CheckpointError` with one line naming the setting the path came from (when known),
the path, and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn

__all__ = ["CheckpointError", "MODEL_IDENTITY_KEY", "PACKAGE_DIR", "find_checkpoint", "read_state_dict", "file_task",
           "load_weights", "save_weights", "load_training_checkpoint"]

MODEL_IDENTITY_KEY = "dfvo_model"
PACKAGE_DIR = Path(__file__).resolve().parents[1]
PREFIXES = ("", "net.", "flow_net.", "flow.", "depth_net.", "depth.", "pose_net.", "model.")


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, unsafe, or does not hold the expected network."""


def _where(path: Path, setting: str | None) -> str:
    return f"{setting}={path}" if setting else str(path)


def _reason(err: Exception) -> str:
    """A one-line reason of a failed read (torch's weights-only message is long; keep the unpickler's reason)."""
    text = str(err)
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return f"{type(err).__name__}: {lines[0][:200] if lines else 'unreadable'}"


def find_checkpoint(path: str | Path | None, setting: str = "checkpoint") -> Path:
    """Resolve a checkpoint path: absolute or existing as given; else relative to the installed package, where the
    shipped weights live (``checkpoints/flow.safetensors`` is ``dfvo/checkpoints/flow.safetensors``). The path as
    given is returned when neither exists (the reader then says it does not exist)."""
    if not path:
        raise CheckpointError(f"{setting} is not set; expected a weights file (.safetensors, .pt or .ckpt)")
    p = Path(path)
    if not (p.is_absolute() or p.exists()) and (PACKAGE_DIR / p).exists():
        p = PACKAGE_DIR / p
    if p.is_dir():
        raise CheckpointError(_folder_message(p, setting))
    return p


WEIGHT_SUFFIXES = (".safetensors", ".pt", ".pth", ".ckpt")


def _folder_message(path: Path, setting: str | None) -> str:
    """``SETTING=PATH is a folder; expected a .safetensors file`` (and the weights files it holds, if any)."""
    found = sorted(p.name for p in path.iterdir() if p.suffix in WEIGHT_SUFFIXES)[:3]
    inside = f" (it holds {', '.join(found)}: pass one of them)" if found else ""
    return f"{_where(path, setting)} is a folder; expected a .safetensors file (or a .pt/.ckpt weights file){inside}"


def read_state_dict(path: str | Path, expected: str, setting: str | None = None
                    ) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The tensors and string metadata of a weights file (see the module docstring for the formats).

    Args:
        path: the file. expected: what it should hold, for messages (``"depth network DepthNet"``).
        setting: the config key the path came from, for messages (``"model.init_from"``).
    """
    path = Path(path)
    where = _where(path, setting)
    if path.is_dir():
        raise CheckpointError(_folder_message(path, setting))
    if not path.is_file():
        raise CheckpointError(f"{where}: {expected} checkpoint does not exist (expected a .safetensors/.pt/.ckpt "
                              f"file holding a {expected})")
    if path.suffix == ".safetensors":
        from safetensors import safe_open
        try:
            with safe_open(str(path), framework="pt") as f:
                return {k: f.get_tensor(k) for k in f.keys()}, dict(f.metadata() or {})
        except Exception as err:  # safetensors raises its own error types
            raise CheckpointError(f"{where}: not a readable safetensors file ({_reason(err)}); expected a "
                                  f"{expected}") from err
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # UnpicklingError, EOFError, RuntimeError (bad zip), ...: all mean "unreadable"
        raise CheckpointError(f"{where}: cannot be loaded as weights only ({_reason(err)}); expected a {expected} "
                              "as .safetensors or a state dict of tensors (pickled objects are not loaded)") from err
    meta: dict[str, str] = {}
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        meta = {k: str(v) for k, v in obj.items() if isinstance(v, str | int | float)}
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise CheckpointError(f"{where}: holds {type(obj).__name__}, not a state dict of tensors; expected a "
                              f"{expected}")
    return obj, meta


def file_task(meta: dict[str, str]) -> str | None:
    """The model kind (``flow``, ``depth``) a weights file says it holds: the ``task`` metadata of an export, or the
    task of the model identity (``"depth:depth_stereo"``) of a training checkpoint; None when it says nothing."""
    if meta.get("task"):
        return str(meta["task"])
    identity = meta.get(MODEL_IDENTITY_KEY)
    return str(identity).split(":", 1)[0] if identity else None


def load_weights(model: nn.Module, path: str | Path, expected: str, setting: str | None = None,
                 task: str | None = None, contents: tuple[dict[str, torch.Tensor], dict[str, str]] | None = None
                 ) -> dict[str, str]:
    """Fill ``model`` from the weights file ``path`` (tensors cast to the model's dtypes).

    Args:
        model: the network (its architecture must match the file).
        path: the weights file. expected: the network's name for messages (``"flow network FlowNet('small')"``).
        setting: the config key the path came from, for messages.
        task: the model kind the file must hold (``flow``, ``depth``), checked against what the file says it holds
            (:func:`file_task`) before the tensors; None: no check.
        contents: the file's ``(state, metadata)`` when the caller has already read it (:func:`read_state_dict`, e.g.
            to size the network by it); None: read here.

    Returns:
        The file's string metadata.

    Raises:
        CheckpointError: missing or unreadable file, a file of another model kind, no prefix matching the model,
            missing/unexpected keys, shapes that differ (another variant).
    """
    path = Path(path)
    where = _where(path, setting)
    state, meta = contents if contents is not None else read_state_dict(path, expected, setting)
    found = file_task(meta)
    if task is not None and found is not None and found != task:
        what = f"model identity {meta[MODEL_IDENTITY_KEY]!r}" if meta.get(MODEL_IDENTITY_KEY) else f"task={found!r}"
        raise CheckpointError(f"{where}: holds a {found} model ({what}), expected a {expected} (a {task} "
                              "checkpoint or weights file)")
    wanted = model.state_dict()
    best, best_hits = "", -1
    for prefix in PREFIXES:
        hits = sum(1 for k in state if k.startswith(prefix) and k[len(prefix):] in wanted)
        if hits > best_hits:
            best, best_hits = prefix, hits
    sub = {k[len(best):]: v for k, v in state.items() if k.startswith(best)}
    missing = sorted(set(wanted) - set(sub))
    unexpected = sorted(set(sub) - set(wanted))
    if best_hits <= 0 or missing or unexpected:
        raise CheckpointError(f"{where}: does not hold a {expected} ({len(missing)} missing keys e.g. {missing[:3]}, "
                              f"{len(unexpected)} unexpected e.g. {unexpected[:3]})")
    bad = [k for k, v in sub.items() if v.shape != wanted[k].shape]
    if bad:
        k = bad[0]
        raise CheckpointError(f"{where}: tensor {k} has shape {tuple(sub[k].shape)}, the {expected} expects "
                              f"{tuple(wanted[k].shape)} (another network variant?)")
    corrupt = _non_finite(sub)
    if corrupt:
        k, n = corrupt[0]
        raise CheckpointError(f"{where}: NaN or inf values in {len(corrupt)} of {len(sub)} tensors (e.g. {k}: {n} of "
                              f"{sub[k].numel()} values); the file is corrupted (its header reads, its weights do "
                              f"not): copy or export the {expected} again")
    model.load_state_dict({k: v.to(wanted[k].dtype) for k, v in sub.items()})
    return meta


def _non_finite(state: dict[str, torch.Tensor]) -> list[tuple[str, int]]:
    """``(name, count)`` of the floating-point tensors of ``state`` that hold NaN or inf values."""
    out = []
    for k, v in state.items():
        if v.is_floating_point():
            n = int((~torch.isfinite(v)).sum())
            if n:
                out.append((k, n))
    return out


def save_weights(model: nn.Module, path: str | Path, metadata: dict[str, Any],
                 dtype: torch.dtype = torch.float16) -> Path:
    """Write the weights of ``model`` as ``.safetensors`` (floating tensors cast to ``dtype``), with ``metadata``
    (values stored as strings). Written to a temporary file and renamed, so a reader never sees half a file."""
    from safetensors.torch import save_file

    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(f"{path}: expected a .safetensors path for exported weights")
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: (v.detach().to(dtype) if v.is_floating_point() else v.detach()).contiguous().cpu()
             for k, v in model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(state, str(tmp), metadata={k: str(v) for k, v in metadata.items()})
    tmp.chmod(0o644)  # safetensors writes 0600; exported weights are meant to be shared
    tmp.replace(path)
    return path


def load_training_checkpoint(path: str | Path, setting: str = "ckpt_path", identity: str | None = None
                             ) -> dict[str, Any]:
    """A resumable Lightning checkpoint written by ``train.py`` (optimiser state included, so it is unpickled:
    only load checkpoints you wrote).

    Args:
        path: the ``.ckpt`` file. setting: the config key it came from, for messages.
        identity: when given, the ``"task:name"`` the checkpoint must have been written for.

    Raises:
        CheckpointError: missing or unreadable file, not a Lightning checkpoint, no dfvo model identity, or
            another model's identity.
    """
    path = Path(path)
    expected = "a last.ckpt / best-*.ckpt written by train.py"
    if not path.is_file():
        raise CheckpointError(f"{setting}={path}: no such checkpoint file (expected {expected})")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:
        raise CheckpointError(f"{setting}={path}: cannot be read as a checkpoint ({_reason(err)}); expected "
                              f"{expected}") from err
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        found = f"a dict with keys {sorted(map(str, ckpt))[:6]}" if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(f"{setting}={path}: holds {found}, not a Lightning checkpoint (no 'state_dict'); "
                              f"expected {expected}")
    if identity is not None:
        found = ckpt.get(MODEL_IDENTITY_KEY)
        if found is None:
            raise CheckpointError(f"{setting}={path}: the checkpoint has no dfvo model identity "
                                  f"({MODEL_IDENTITY_KEY!r}): it was written by another program or an older dfvo, so "
                                  f"it cannot be resumed as a {identity!r} run; start without {setting} (use "
                                  f"model.init_from={path} to start from its weights)")
        if found != identity:
            raise CheckpointError(f"{setting}={path} holds a {found!r} model, but this run is {identity!r}; pass the "
                                  f"matching model= (or start without {setting})")
    return ckpt
