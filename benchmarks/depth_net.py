"""Speed of the depth network and of one depth-stereo training step on this machine; prints JSON.

    python benchmarks/depth_net.py [--height 192 --width 640 --threads 1 --batch 4 --repeats 5]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch
from omegaconf import OmegaConf

from dfvo.models.depth_net import DepthNet
from dfvo.models.resnet import ResNet18Encoder
from dfvo.training.depth_module import DepthPoseModule


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * sorted(times)[len(times) // 2]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--train-height", type=int, default=96)
    p.add_argument("--train-width", type=int, default=320)
    p.add_argument("--batch", type=int, default=4, help="training batch size")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=5)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    x = torch.rand(1, 3, a.height, a.width)
    net, enc = DepthNet().eval(), ResNet18Encoder(1).eval()
    with torch.no_grad():
        t_depth = _time(lambda: net(x), a.repeats)
        t_enc = _time(lambda: enc(x), a.repeats)
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
    print(json.dumps({
        "machine": f"{platform.processor() or platform.machine()}, torch threads {a.threads}",
        "depth_net_forward_ms": round(t_depth, 1), "encoder_forward_ms": round(t_enc, 1),
        "forward_resolution": f"{a.width}x{a.height}",
        "train_step_ms": round(t_step, 1), "train_resolution": f"{W}x{H}", "train_batch": B,
        "train_model": "depth_stereo (stereo + prev/next with pose net)",
    }))


if __name__ == "__main__":
    main()
