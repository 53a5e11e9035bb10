"""Export a training checkpoint to the small weights-only file that infer.py loads (fp16 safetensors).

    python scripts/export_checkpoint.py flow  runs/flow_cpu2/self/final.ckpt checkpoints/flow.safetensors \
        --height 96 --width 320
    python scripts/export_checkpoint.py depth runs/depth_stereo_cpu_long/checkpoints/last.ckpt \
        checkpoints/depth.safetensors

Every training run already writes this file beside its last checkpoint (``runs/<name>/weights.safetensors``); the
script exports any other checkpoint (a ``best-*.ckpt``, an older run, a state dict). Only the network that inference
needs is kept (the pose network of a depth run is dropped); tensors are stored in float16 (loaded back as float32:
:func:`dfvo.io.checkpoint.load_weights` casts to the model's dtype). The metadata is the one training writes
(:func:`dfvo.training.export.weights_metadata`): the network (``task``, ``variant``, depth range), the input size it
was trained at (``height``/``width``, from ``--height/--width`` or the ``data`` settings stored in a train.py
checkpoint; the inference sources resize to it), the source checkpoint, its step and epoch and model identity. The
exported network is loaded back and compared with the float32 original on a random image before the file is written;
the script fails if they disagree by more than fp16 rounding.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import torch

from dfvo.io.checkpoint import MODEL_IDENTITY_KEY, CheckpointError, load_weights, read_state_dict, save_weights
from dfvo.models.depth_net import DepthNet, network_width
from dfvo.models.flow_net import FlowNet
from dfvo.sources.networks import VARIANTS
from dfvo.training.export import weights_metadata


def _checkpoint_info(path: Path) -> dict:
    """Step, epoch, model identity, trained size (``data.height``/``width``) and depth network width
    (``model.width_multiplier``) of a train.py checkpoint."""
    obj = torch.load(path, map_location="cpu", weights_only=False) if path.suffix == ".ckpt" else {}
    cfg = ((obj.get("hyper_parameters") or {}).get("cfg") or {}) if isinstance(obj, dict) else {}
    data, model = cfg.get("data") or {}, cfg.get("model") or {}
    return {"global_step": obj.get("global_step"), "epoch": obj.get("epoch"), "identity": obj.get(MODEL_IDENTITY_KEY),
            "height": data.get("height"), "width": data.get("width"), "net_width": model.get("width_multiplier")}


def build_network(task: str, path: Path, variant: str | None, net_width: float | None = None
                  ) -> tuple[torch.nn.Module, dict[str, str]]:
    """The network of ``task`` ("flow" or "depth", of channel multiplier ``net_width``; None: the file's own, see
    :func:`dfvo.models.depth_net.network_width`) filled from ``path``, and metadata describing it."""
    if task == "depth":
        contents = read_state_dict(path, "depth network DepthNet")
        net = DepthNet(width=network_width(contents[1], str(path), contents[0]) if net_width is None else net_width)
        load_weights(net, path, "depth network DepthNet", contents=contents)
        return net.eval(), {"task": "depth", "min_depth": str(net.min_depth), "max_depth": str(net.max_depth),
                            "width_multiplier": repr(net.width)}
    for name in [variant] if variant else list(VARIANTS):
        net = FlowNet(name)
        try:
            load_weights(net, path, f"flow network FlowNet({name!r})")
            return net.eval(), {"task": "flow", "variant": name}
        except CheckpointError:
            if variant:
                raise
    raise CheckpointError(f"{path}: holds no FlowNet variant of {VARIANTS}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("task", choices=("flow", "depth"))
    p.add_argument("checkpoint", type=Path, help="training checkpoint (.ckpt) or state dict")
    p.add_argument("out", type=Path, help="output .safetensors")
    p.add_argument("--variant", default=None, help="FlowNet variant (default: the one the checkpoint holds)")
    p.add_argument("--height", type=int, default=None,
                   help="input height the network was trained at (default: the checkpoint's data.height)")
    p.add_argument("--width", type=int, default=None,
                   help="input width the network was trained at (default: the checkpoint's data.width)")
    args = p.parse_args()
    if args.out.suffix != ".safetensors":
        raise SystemExit(f"out={args.out}: expected a .safetensors path")
    info = _checkpoint_info(args.checkpoint)
    height, width = args.height or info["height"], args.width or info["width"]
    if not (height and width):
        raise SystemExit(f"{args.checkpoint}: records no trained size (data.height/width); pass --height and --width")

    net, net_meta = build_network(args.task, args.checkpoint, args.variant,
                                  None if info["net_width"] is None else float(info["net_width"]))
    meta = weights_metadata(net_meta, int(height), int(width), global_step=info["global_step"], epoch=info["epoch"],
                            source=args.checkpoint, identity=info["identity"])
    state = {k: v.detach().to(torch.float16).contiguous() if v.is_floating_point() else v.contiguous()
             for k, v in net.state_dict().items()}
    # check: the fp16 copy gives the same output as the original up to fp16 rounding
    back = type(net)(meta["variant"]) if args.task == "flow" else DepthNet(net.min_depth, net.max_depth,
                                                                                         width=net.width)
    back.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    back.eval()
    torch.manual_seed(0)
    x = torch.rand(1, 3, int(height), int(width))
    with torch.no_grad():
        if args.task == "flow":
            y = torch.rand(1, 3, int(height), int(width))
            a, b = net(x, y), back(x, y)
            err = float((a - b).abs().max() / a.abs().max().clamp_min(1e-6))
        else:
            a, b = net.depth(x), back.depth(x)
            err = float(((a - b).abs() / a).max())
    if err > 1e-2:
        raise SystemExit(f"fp16 export differs from the float32 network by {err:.3g} (relative); not written")
    save_weights(net, args.out, meta)
    digest = hashlib.sha256(args.out.read_bytes()).hexdigest()[:16]
    print(json.dumps({"out": str(args.out), "bytes": args.out.stat().st_size, "sha256_16": digest,
                      "fp16_relative_error": round(err, 6), **meta}))


if __name__ == "__main__":
    main()
