"""A real (CPU) flow training run: supervised on the synthetic world, then self-supervised on KITTI raw.

Prints one JSON line per logged step and one per evaluation (held-out synthetic worlds, benchmarks/flow_net.py
metrics), so the log is the curve. Datasets are rendered/decoded once into memory (the synthetic renderer
costs ~0.3 s a frame), then the Lightning module ``FlowModule`` trains on them with the configs'
settings. Example (what the flow engineer ran, 1 torch thread, 96x320):

    nohup nice -n 5 python benchmarks/flow_training_run.py --out runs/flow_cpu --sup-minutes 30 \
        --self-minutes 15 > runs/flow_cpu.log 2>&1 &
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import lightning as L
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf
from torch.utils.data import DataLoader, Dataset

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from flow_net import evaluate_pairs, render_pairs  # noqa: E402

from dfvo.data.image_io import list_images, read_image  # noqa: E402
from dfvo.data.synthetic import SyntheticFlowDataset  # noqa: E402
from dfvo.models.flow_net import FlowNet  # noqa: E402
from dfvo.training.flow_module import FlowModule  # noqa: E402


class Cached(Dataset):
    """In-memory items; with ``gray_prob`` > 0 each item's images become grey (luma in all three channels) with
    that probability, so a network trained on colour also sees KITTI odometry's greyscale cameras."""

    def __init__(self, items: list[dict], gray_prob: float = 0.0) -> None:
        self.items, self.gray_prob = items, gray_prob

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        item = self.items[i]
        if self.gray_prob > 0 and torch.rand(()) < self.gray_prob:
            luma = torch.tensor([0.299, 0.587, 0.114]).view(3, 1, 1)
            item = {k: (v * luma).sum(0, keepdim=True).expand(3, -1, -1).clone() if k.startswith("image") else v
                    for k, v in item.items()}
        return item


def synthetic_items(seeds: list[int], num_frames: int, h: int, w: int) -> list[dict]:
    ds = SyntheticFlowDataset(seeds, num_frames=num_frames, height=h, width=w)
    keep = ("image", "image_next", "flow_fwd", "flow_bwd", "flow_fwd_valid", "flow_bwd_valid")
    return [{k: v for k, v in ds[i].items() if k in keep} for i in range(len(ds))]


def kitti_raw_items(root: Path, h: int, w: int) -> list[dict]:
    """Temporal snippets (image_prev, image, image_next) of every drive's image_02 under ``root``."""
    items = []
    for drive in sorted(root.glob("*_sync")):
        frames = [F.interpolate(read_image(p)[None], size=(h, w), mode="area")[0]
                  for p in list_images(drive / "image_02" / "data", "KITTI raw image_02/data")]
        for k in range(1, len(frames) - 1):
            items.append({"image_prev": frames[k - 1], "image": frames[k], "image_next": frames[k + 1]})
    if not items:
        raise FileNotFoundError(f"no KITTI raw drives (*_sync/image_02/data) under {root}")
    return items


class JsonLog(L.Callback):
    def __init__(self, stage: str, every: int, deadline: float) -> None:
        self.stage, self.every, self.deadline, self.t0 = stage, every, deadline, time.time()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if step % self.every == 0:
            m = {k: round(float(v), 4) for k, v in trainer.callback_metrics.items() if k.startswith("train/")}
            print(json.dumps({"stage": self.stage, "step": step, "minutes": round((time.time() - self.t0) / 60, 2),
                              **m}), flush=True)
        if time.time() > self.deadline:
            trainer.should_stop = True


def run_stage(name: str, cfg, items: list[dict], out: Path, minutes: float, batch: int,
              eval_pairs: list[dict], gray_prob: float = 0.0) -> Path:
    module = FlowModule(cfg)
    logger = L.pytorch.loggers.TensorBoardLogger(str(out), name=name)
    ckpt = L.pytorch.callbacks.ModelCheckpoint(dirpath=str(out / name), save_last=True, every_n_train_steps=100)
    stop = JsonLog(name, 25, time.time() + 60 * minutes)
    trainer = L.Trainer(max_epochs=10_000, logger=logger, callbacks=[ckpt, stop],
                        accelerator="cpu", devices=1, enable_progress_bar=False, log_every_n_steps=5,
                        limit_val_batches=0, num_sanity_val_steps=0, enable_model_summary=False)
    trainer.fit(module, DataLoader(Cached(items, gray_prob), batch_size=batch, shuffle=True, drop_last=True))
    path = out / name / "final.ckpt"
    trainer.save_checkpoint(path)
    print(json.dumps({"stage": name, "eval_after": True, "steps": trainer.global_step, "checkpoint": str(path),
                      **evaluate_pairs(module.net, eval_pairs)}), flush=True)
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/flow_cpu")
    p.add_argument("--variant", default="small")
    p.add_argument("--height", type=int, default=96)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--train-seeds", default="0,1,2,3,4,5")
    p.add_argument("--num-frames", type=int, default=60)
    p.add_argument("--eval-seeds", default="100,101")
    p.add_argument("--eval-frames", type=int, default=40)
    p.add_argument("--sup-minutes", type=float, default=30)
    p.add_argument("--self-minutes", type=float, default=15)
    p.add_argument("--sup-lr", type=float, default=1e-4)
    p.add_argument("--self-lr", type=float, default=1e-5)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--kitti-raw", default="../shared/data/kitti_raw/2011_09_26")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--init", default=None, help="start the supervised stage from this FlowModule .ckpt / FlowNet "
                   "state dict (e.g. an earlier run's supervised/final.ckpt)")
    p.add_argument("--gray-prob", type=float, default=0.0, help="probability of greyscale training pairs")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    h, w = args.height, args.width
    t0 = time.time()
    eval_pairs = render_pairs([int(s) for s in args.eval_seeds.split(",")], args.eval_frames, h, w, stride=2)
    train = synthetic_items([int(s) for s in args.train_seeds.split(",")], args.num_frames, h, w)
    print(json.dumps({"rendered": len(train), "eval_pairs": len(eval_pairs),
                      "minutes": round((time.time() - t0) / 60, 2)}), flush=True)

    def model_cfg(mode: str, lr: float, init_from: str | None):
        return OmegaConf.create({"model": {"task": "flow", "mode": mode, "variant": args.variant, "lr": lr,
                                           "lr_milestones": [10_000], "lr_gamma": 0.1, "init_from": init_from,
                                           "log_images_every": 100,
                                           "loss": {"alpha": 0.85, "w_smooth": 0.1, "w_consistency": 5e-3,
                                                    "occlusion": True}}})

    print(json.dumps({"stage": "untrained", **evaluate_pairs(FlowNet(args.variant), eval_pairs)}), flush=True)
    sup = run_stage("supervised", model_cfg("supervised", args.sup_lr, args.init), train, out, args.sup_minutes,
                    args.batch, eval_pairs, args.gray_prob)
    if args.self_minutes <= 0:
        return
    kitti = kitti_raw_items(Path(args.kitti_raw), h, w)
    run_stage("self", model_cfg("self", args.self_lr, str(sup)), kitti, out, args.self_minutes, max(1, args.batch // 2),
              eval_pairs, args.gray_prob)


if __name__ == "__main__":
    main()
