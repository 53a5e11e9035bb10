"""Speed of the depth network and of one depth-stereo training step on this machine; prints JSON.

    python benchmarks/depth_net.py [--height 192 --width 640 --threads 1 --batch 4 --repeats 5] [--skip-train]
    python benchmarks/depth_net.py --widths 1 0.75 0.5 --height 96 --width 320 --batch 4 --repeats 9

``--widths``: only the inference path (``DepthNet.depth`` of a batch) of networks of these channel multipliers
(``model.width``), interleaved in one process; ``width_ms`` per width and ``width_ratio`` to the first.

``depth_net_forward_ms`` is the inference path that the pipeline uses (``DepthNet.depth``, called by
``dfvo.sources.networks.NetworkDepth``: scale-0 head only, folded batch norms, channels_last);
``depth_net_train_forward_ms`` the training forward (all 4 disparity scales) in eval mode without gradients.
The forward variants are timed interleaved (one call of each per round, order alternating) so that a shared,
busy machine affects them alike; ``inference_speedup`` is the ratio of their medians.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable

import torch
from omegaconf import OmegaConf

from dfvo.models.depth_net import DepthNet
from dfvo.models.resnet import ResNet18Encoder
from dfvo.training.depth_module import DepthPoseModule


def _time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn()`` in ms over ``repeats`` calls, after one warm-up call."""
    return _time_interleaved({"fn": fn}, repeats)["fn"]


def _time_interleaved(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median wall time in ms of each function, calling them in turn (order reversed every other round)."""
    for fn in fns.values():
        fn()  # warm-up (also builds DepthNet's cached inference copy)
    times: dict[str, list[float]] = {k: [] for k in fns}
    names = list(fns)
    for r in range(repeats):
        for k in names if r % 2 == 0 else names[::-1]:
            t0 = time.perf_counter()
            fns[k]()
            times[k].append(time.perf_counter() - t0)
    return {k: 1000.0 * sorted(t)[len(t) // 2] for k, t in times.items()}


def compare_widths(widths: list[float], batch: int, height: int, width: int, repeats: int, threads: int) -> dict:
    """Median ms of ``DepthNet(width=w).depth`` on a (batch,3,height,width) input per width, interleaved."""
    x = torch.rand(batch, 3, height, width)
    nets = {w: DepthNet(width=w).eval() for w in widths}
    with torch.no_grad():
        t = _time_interleaved({str(w): (lambda n=n: n.depth(x)) for w, n in nets.items()}, repeats)
    first = t[str(widths[0])]
    return {"machine": f"{platform.processor() or platform.machine()}, torch threads {threads}",
            "input": f"{batch}x3x{height}x{width}", "width_ms": {k: round(v, 1) for k, v in t.items()},
            "width_ratio": {k: round(v / first, 3) for k, v in t.items()},
            "parameters_millions": {str(w): round(sum(p.numel() for p in n.parameters()) / 1e6, 2)
                                    for w, n in nets.items()}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--train-height", type=int, default=96)
    p.add_argument("--train-width", type=int, default=320)
    p.add_argument("--batch", type=int, default=4, help="training batch size")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--skip-train", action="store_true", help="time the forward passes only")
    p.add_argument("--widths", type=float, nargs="+", help="compare the inference path of these network widths")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    if a.widths:
        print(json.dumps(compare_widths(a.widths, a.batch, a.height, a.width, a.repeats, a.threads)))
        return
    x = torch.rand(1, 3, a.height, a.width)
    net, enc = DepthNet().eval(), ResNet18Encoder(1).eval()
    with torch.no_grad():
        forwards = {"depth": lambda: net.depth(x), "train_forward": lambda: net(x), "encoder": lambda: enc(x)}
        t = _time_interleaved(forwards, a.repeats)
    result = {
        "machine": f"{platform.processor() or platform.machine()}, torch threads {a.threads}",
        "depth_net_forward_ms": round(t["depth"], 1), "depth_net_train_forward_ms": round(t["train_forward"], 1),
        "inference_speedup": round(t["train_forward"] / t["depth"], 3), "encoder_forward_ms": round(t["encoder"], 1),
        "forward_resolution": f"{a.width}x{a.height}",
    }
    if a.skip_train:
        print(json.dumps(result))
        return
    cfg = OmegaConf.create({"model": {"task": "depth", "name": "depth_stereo", "stereo": True, "temporal": True}})
    module = DepthPoseModule(cfg)
    opt = torch.optim.Adam(module.parameters(), lr=1e-4)
    H, W, B = a.train_height, a.train_width, a.batch
    K = torch.tensor([[0.58 * W, 0, 0.5 * W], [0, 1.92 * H, 0.5 * H], [0, 0, 1.0]]).expand(B, 3, 3)
    T = torch.eye(4).expand(B, 4, 4).clone()
    T[:, 0, 3] = -0.54
    batch = {k: torch.rand(B, 3, H, W) for k in ("image", "image_prev", "image_next", "image_right")}
    batch.update(K=K, T_right_left=T)

    def step() -> None:
        opt.zero_grad()
        loss, _, _ = module._losses(batch)
        loss.backward()
        opt.step()

    t_step = _time(step, max(2, a.repeats // 2))
    result.update(train_step_ms=round(t_step, 1), train_resolution=f"{W}x{H}", train_batch=B,
                  train_model="depth_stereo (stereo + prev/next with pose net)")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
