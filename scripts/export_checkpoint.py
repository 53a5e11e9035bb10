"""Export a training checkpoint to the small weights-only file that infer.py loads (fp16 safetensors).

    python scripts/export_checkpoint.py flow  runs/flow_cpu2/self/final.ckpt checkpoints/flow.safetensors \
        --height 96 --width 320
    python scripts/export_checkpoint.py depth runs/depth_stereo_cpu_long/checkpoints/last.ckpt \
        checkpoints/depth.safetensors --height 96 --width 320

Only the network that inference needs is kept (the pose network of a depth run is dropped); tensors are stored in
float16 (loaded back as float32: :func:`dfvo.io.checkpoint.load_weights` casts to the model's dtype). The
metadata records the network (``task``, ``variant``), the input size it was trained at (``height``/``width``:
the inference sources resize to it), its depth range, the source checkpoint and its training step, so a model
card can be checked against the file. The exported network is loaded back and compared with the float32 original
on a random image before the file is written; the script fails if they disagree by more than fp16 rounding.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dfvo.io.checkpoint import CheckpointError, load_weights  # noqa: E402
from dfvo.models.depth_net import DepthNet  # noqa: E402
from dfvo.models.flow_net import FlowNet  # noqa: E402
from dfvo.sources.networks import VARIANTS  # noqa: E402


def _checkpoint_info(path: Path) -> dict[str, str]:
    obj = torch.load(path, map_location="cpu", weights_only=False) if path.suffix == ".ckpt" else {}
    info = {}
    for key in ("global_step", "epoch"):
        if key in obj:
            info[key] = str(obj[key])
    return info


def build_network(task: str, path: Path, variant: str | None) -> tuple[torch.nn.Module, dict[str, str]]:
    """The network of ``task`` ("flow" or "depth") filled from ``path``, and metadata describing it."""
    if task == "depth":
        net = DepthNet()
        load_weights(net, path, "depth network DepthNet")
        return net.eval(), {"task": "depth", "min_depth": str(net.min_depth), "max_depth": str(net.max_depth)}
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
    p.add_argument("--height", type=int, required=True, help="input height the network was trained at")
    p.add_argument("--width", type=int, required=True, help="input width the network was trained at")
    args = p.parse_args()
    if args.out.suffix != ".safetensors":
        raise SystemExit(f"out={args.out}: expected a .safetensors path")
    from safetensors.torch import save_file

    net, meta = build_network(args.task, args.checkpoint, args.variant)
    meta.update({"height": str(args.height), "width": str(args.width), "source": str(args.checkpoint),
                 **_checkpoint_info(args.checkpoint)})
    state = {k: v.detach().to(torch.float16).contiguous() if v.is_floating_point() else v.contiguous()
             for k, v in net.state_dict().items()}
    # check: the fp16 copy gives the same output as the original up to fp16 rounding
    back = type(net)(meta["variant"]) if args.task == "flow" else DepthNet(net.min_depth, net.max_depth)
    back.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    back.eval()
    torch.manual_seed(0)
    x = torch.rand(1, 3, args.height, args.width)
    with torch.no_grad():
        if args.task == "flow":
            y = torch.rand(1, 3, args.height, args.width)
            a, b = net(x, y), back(x, y)
            err = float((a - b).abs().max() / a.abs().max().clamp_min(1e-6))
        else:
            a, b = net.depth(x), back.depth(x)
            err = float(((a - b).abs() / a).max())
    if err > 1e-2:
        raise SystemExit(f"fp16 export differs from the float32 network by {err:.3g} (relative); not written")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_file(state, str(args.out), metadata=meta)
    digest = hashlib.sha256(args.out.read_bytes()).hexdigest()[:16]
    print(json.dumps({"out": str(args.out), "bytes": args.out.stat().st_size, "sha256_16": digest,
                      "fp16_relative_error": round(err, 6), **meta}))


if __name__ == "__main__":
    main()
