"""A resumable CPU (or GPU) flow training run: supervised on the synthetic world's driving distribution, then mixed
with self-supervised KITTI raw pairs. Plain PyTorch loop around :class:`dfvo.models.flow_net.FlowNet` and the losses
of :mod:`dfvo.losses.flow_losses` (the same ones ``FlowModule`` uses), so one process controls data caching,
resumption and the evaluation curve.

Data (the network's input size ``--height x --width``, 96x320 by default, the size inference runs it at):
    - synthetic: ``--worlds`` training worlds (seeds 0.., below the held-out 1000) cycling through ``--scenarios``
      (drive, city, straight, highway), speed drawn per world in ``--speed`` (m/frame), pairs (k, k+s) for every
      s of ``--frame-skips``; pairs whose largest true flow exceeds ``--max-flow`` pixels of the working size
      (``--render-scale`` x the network size, 640x192) are dropped. Rendered at the working size and resized the
      way inference resizes (antialiased bilinear; flows block-averaged over valid pixels), cached per world
      under ``--cache`` (a restart does not render again). Half of the worlds vary their exposure, all have
      sensor noise in [0, 0.02].
    - augmentation: horizontal flip (u negated), 30 % greyscale pairs (KITTI odometry's cameras), independent
      brightness/contrast/gamma jitter per image (exposure changes between frames).
    - KITTI raw (phase ``mix``): pairs (k, k+s), s in ``--frame-skips``, of every drive under ``--kitti-raw``,
      decoded as inference does (bilinear to 640x192, antialiased to the network size); self-supervised loss
      (photometric SSIM+L1, smoothness, forward-backward consistency) added with weight ``--self-weight``.

Phases: ``--sup-steps`` supervised steps, then ``--mix-steps`` steps of supervised + self-supervised batches;
the learning rate drops by 10x for the last quarter of each phase. Every ``--save-every`` steps ``OUT/last.pt``
(network, optimiser, step) and ``OUT/weights.safetensors`` (the inference export, fp16, with the network size in
its metadata) are rewritten; a rerun with the same ``--out`` resumes from ``last.pt``. Every ``--eval-every``
steps: AEPE and the forward-backward-selected correspondences' AEPE on held-out worlds (seeds 1002, 1003 of each
scenario: never trained on, and not the benchmark's 1000/1001), through the inference path (working size 640x192,
network at its size). One JSON line per log/eval. Example (the run of issue 13, 1 thread, in the background):

    OMP_NUM_THREADS=1 nohup python benchmarks/flow_training_run.py --out /work/runs/flow_v2 \
        --init dfvo/checkpoints/flow.safetensors --sup-steps 6000 --mix-steps 2000 > /work/runs/flow_v2.log 2>&1 &
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dfvo.data.image_io import list_images, read_image  # noqa: E402
from dfvo.data.synthetic import HELD_OUT_SEED, SyntheticWorld, check_training_seeds  # noqa: E402
from dfvo.io.checkpoint import load_weights, save_weights  # noqa: E402
from dfvo.losses.flow_losses import multiscale_epe, self_supervised_flow_loss  # noqa: E402
from dfvo.matching.consistency import forward_backward_inconsistency  # noqa: E402
from dfvo.matching.selection import select_correspondences  # noqa: E402
from dfvo.models.flow_net import FlowNet  # noqa: E402


def resize_images(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(N,3,H,W) -> size, antialiased bilinear (as :class:`dfvo.sources.networks.NetworkFlow` resizes)."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)


def downsample_flow(flow: torch.Tensor, valid: torch.Tensor, factor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,2,H,W) flow and (N,1,H,W) validity -> /factor: the mean flow of each block's valid pixels (in the small
    image's pixels) and valid where every pixel of the block is."""
    if factor == 1:
        return flow, valid
    v = valid.float()
    s = F.avg_pool2d(flow * v, factor)
    n = F.avg_pool2d(v, factor)
    return s / n.clamp_min(1e-6) / factor, n > 0.999


# ------------------------------------------------------------------------------------------------ synthetic data
def render_world(seed: int, scenario: str, speed: tuple[float, float] | None, frames: int, skips: list[int],
                 size: tuple[int, int], scale: int, max_flow: float, cache: Path, exposure: bool,
                 noise: float, device: str = "cpu") -> dict:
    """Frames (fp16, network size) and pairs (k, k+s) with true flows of one world (cached in ``cache`` on the CPU;
    rendered on ``device``)."""
    h, w = size
    tag = f"{scenario}_s{seed}_{frames}f_{h}x{w}x{scale}_sp{speed}_k{''.join(map(str, skips))}_mf{max_flow:g}"
    path = cache / f"{tag}.pt"
    if path.is_file():
        return torch.load(path)
    world = SyntheticWorld(seed=seed, num_frames=frames, height=h * scale, width=w * scale, scenario=scenario,
                           speed=speed, exposure_change=exposure, noise_std=noise, device=device)
    images = resize_images(torch.stack([world.image(k) for k in range(frames)]), size)
    pairs = []
    for s in skips:
        for k in range(frames - s):
            fwd, vf = world.flow(k, k + s)
            if not bool(vf.any()) or float(fwd.norm(dim=0)[vf[0]].max()) > max_flow:
                continue
            bwd, vb = world.flow(k + s, k)
            ff, vff = downsample_flow(fwd[None], vf[None], scale)
            fb, vfb = downsample_flow(bwd[None], vb[None], scale)
            pairs.append((k, k + s, ff[0].half().cpu(), vff[0].cpu(), fb[0].half().cpu(), vfb[0].cpu()))
    out = {"images": images.half().cpu(), "pairs": pairs, "scenario": scenario, "seed": seed}
    cache.mkdir(parents=True, exist_ok=True)
    torch.save(out, path.with_suffix(".tmp"))
    path.with_suffix(".tmp").replace(path)
    return out


def photometric_jitter(img: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """(N,3,H,W): per-image brightness x[0.8,1.2], contrast x[0.8,1.2], gamma [0.8,1.25] (independent per image)."""
    n = img.shape[0]
    r = torch.rand(n, 3, 1, 1, 1, generator=gen).to(img.device)
    b, c, g = 0.8 + 0.4 * r[:, 0], 0.8 + 0.4 * r[:, 1], torch.exp((r[:, 2] - 0.5) * 0.45)
    mean = img.mean((1, 2, 3), keepdim=True)
    return (((img - mean) * c + mean) * b).clamp(1e-4, 1).pow(g)


def augment(i1: torch.Tensor, i2: torch.Tensor, ff: torch.Tensor, fb: torch.Tensor, vf: torch.Tensor,
            vb: torch.Tensor, gen: torch.Generator, gray_prob: float) -> tuple[torch.Tensor, ...]:
    """Flip (per batch), greyscale (per pair) and photometric jitter (per image) of a supervised batch."""
    if torch.rand((), generator=gen) < 0.5:
        sign = torch.tensor([-1.0, 1.0], device=ff.device).view(1, 2, 1, 1)
        i1, i2, vf, vb = i1.flip(-1), i2.flip(-1), vf.flip(-1), vb.flip(-1)
        ff, fb = ff.flip(-1) * sign, fb.flip(-1) * sign
    gray = (torch.rand(i1.shape[0], 1, 1, 1, generator=gen) < gray_prob).float().to(i1.device)
    luma = torch.tensor([0.299, 0.587, 0.114], device=i1.device).view(1, 3, 1, 1)

    def g(x: torch.Tensor) -> torch.Tensor:
        return gray * (x * luma).sum(1, keepdim=True).expand_as(x) + (1 - gray) * x

    both = photometric_jitter(torch.cat([g(i1), g(i2)]), gen)
    return (*both.split(i1.shape[0]), ff, fb, vf, vb)


class SyntheticPairs:
    """All cached pairs of the training worlds packed into tensors on ``device`` (fp16 images and flows); ``batch(n)``
    draws n of them (with the CPU generator) as float32."""

    def __init__(self, worlds: list[dict], device: str = "cpu") -> None:
        firsts, a, b, flows, valid = [], [], [], [], []
        offset = 0
        for wd in worlds:
            for i, j, ff, vf, fb, vb in wd["pairs"]:
                a.append(offset + i)
                b.append(offset + j)
                flows.append(torch.stack([ff, fb]))
                valid.append(torch.stack([vf, vb]))
            firsts.append(offset)
            offset += wd["images"].shape[0]
        self.images = torch.cat([wd["images"] for wd in worlds]).to(device)
        self.a, self.b = torch.tensor(a, device=device), torch.tensor(b, device=device)
        self.flows, self.valid = torch.stack(flows).to(device), torch.stack(valid).to(device)
        self.index = range(len(a))

    def batch(self, n: int, gen: torch.Generator) -> tuple[torch.Tensor, ...]:
        pick = torch.randint(len(self.index), (n,), generator=gen).to(self.images.device)
        flows, valid = self.flows[pick].float(), self.valid[pick]
        return (self.images[self.a[pick]].float(), self.images[self.b[pick]].float(), flows[:, 0], flows[:, 1],
                valid[:, 0], valid[:, 1])


def kitti_pairs(root: Path, size: tuple[int, int], skips: list[int],
                working: tuple[int, int] = (192, 640)) -> tuple[torch.Tensor, list[tuple[int, int]]]:
    """Frames (N,3,h,w) fp16 of every KITTI raw drive under ``root`` and pairs (k, k+s) within each drive."""
    frames, pairs = [], []
    for drive in sorted(root.glob("*_sync")):
        paths = list_images(drive / "image_02" / "data", "KITTI raw image_02/data")
        first = len(frames)
        for path in paths:
            frames.append(resize_images(read_image(path, size=working)[None], size)[0].half())
        pairs += [(first + k, first + k + s) for s in skips for k in range(len(paths) - s)]
    if not frames:
        raise FileNotFoundError(f"--kitti-raw {root}: no KITTI raw drives (*_sync/image_02/data)")
    return torch.stack(frames), pairs


# ------------------------------------------------------------------------------------------------ evaluation
@torch.no_grad()
def evaluate(net: FlowNet, evals: list[dict], size: tuple[int, int]) -> dict[str, dict[str, float]]:
    """Per scenario: AEPE over visible pixels and over the local-best-K selected correspondences (0.1 px test),
    the flow computed the way inference does (working-size images resized to the network size, flow back)."""
    net.eval()
    out: dict[str, dict[str, float]] = {}
    device = next(net.parameters()).device
    for ev in evals:
        i1, i2, gt, valid = (ev[k].to(device) for k in ("image", "image_next", "flow", "valid"))
        H, W = gt.shape[-2:]
        fwd, bwd = net.forward_backward(resize_images(i1, size), resize_images(i2, size))
        fwd, bwd = fwd.float(), bwd.float()
        scale = torch.tensor([W / size[1], H / size[0]], device=device).view(1, 2, 1, 1)
        fwd = F.interpolate(fwd, size=(H, W), mode="bilinear", align_corners=False) * scale
        bwd = F.interpolate(bwd, size=(H, W), mode="bilinear", align_corners=False) * scale
        err = (fwd - gt).norm(dim=1, keepdim=True)
        sel = select_correspondences(fwd, forward_backward_inconsistency(fwd, bwd), method="best_n", num=2000)
        e_sel = []
        for b in range(fwd.shape[0]):
            m = sel.mask[b]
            pix = sel.pts_i[b][m].long()
            e_sel.append(err[b, 0, pix[:, 1], pix[:, 0]][valid[b, 0, pix[:, 1], pix[:, 0]]])
        e_sel_all = torch.cat(e_sel)
        out[ev["name"]] = {"aepe": round(float(err[valid].mean()), 3),
                           "bestn_aepe": round(float(e_sel_all.mean()), 3) if len(e_sel_all) else None}
    net.train()
    return out


def eval_sets(scenarios: list[str], cache: Path, frames: int = 12, device: str = "cpu") -> list[dict]:
    """Held-out pairs (seeds 1002, 1003 of each scenario, every 2nd pair) at the working size 192x640."""
    sets = []
    for sc in scenarios:
        path = cache / f"eval_{sc}_{frames}f.pt"
        if not path.is_file():
            rows = []
            for seed in (HELD_OUT_SEED + 2, HELD_OUT_SEED + 3):
                world = SyntheticWorld(seed=seed, num_frames=frames, height=192, width=640, scenario=sc,
                                       speed=(0.3, 3.0) if sc == "straight" else None, device=device)
                for k in range(0, frames - 1, 2):
                    f, v = world.flow(k, k + 1)
                    rows.append(tuple(x.cpu() for x in (world.image(k), world.image(k + 1), f, v)))
            cache.mkdir(parents=True, exist_ok=True)
            torch.save({"name": sc, **{key: torch.stack(c) for key, c in
                                       zip(("image", "image_next", "flow", "valid"), zip(*rows))}}, path)
        sets.append(torch.load(path))
    return sets


# ------------------------------------------------------------------------------------------------ main loop
def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--variant", default="small")
    p.add_argument("--height", type=int, default=96)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--render-scale", type=int, default=2, help="render at this multiple of the network size")
    p.add_argument("--worlds", type=int, default=24)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--scenarios", default="drive,city,straight,highway")
    p.add_argument("--speed", default="0.3,3.0", help="lo,hi m/frame drawn per world ('none': the scenario's)")
    p.add_argument("--frame-skips", default="1,2,3")
    p.add_argument("--max-flow", type=float, default=160.0, help="drop pairs with a larger true flow (working px)")
    p.add_argument("--cache", default="/work/runs/flow_cache")
    p.add_argument("--init", default=None, help="FlowNet weights to start from (.safetensors / .pt / .ckpt)")
    p.add_argument("--sup-steps", type=int, default=6000)
    p.add_argument("--mix-steps", type=int, default=0)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--mix-lr", type=float, default=2e-5)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--kitti-batch", type=int, default=2)
    p.add_argument("--self-weight", type=float, default=1.0)
    p.add_argument("--gray-prob", type=float, default=0.3)
    p.add_argument("--kitti-raw", default="/work/shared/data/kitti_raw/2011_09_26")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", help="training device (cpu, cuda, auto)")
    p.add_argument("--render-device", default=None, help="where the synthetic world renders (default: --device)")
    p.add_argument("--amp", choices=("none", "bf16"), default="none", help="bf16 autocast (GPU)")
    p.add_argument("--channels-last", action="store_true", help="NHWC convolutions (GPU)")
    p.add_argument("--log-every", type=int, default=25)
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--save-every", type=int, default=100)
    p.add_argument("--max-minutes", type=float, default=1e9, help="stop (saving) after this much wall time (from the "
                   "start, rendering included); the phases and learning-rate drops follow the time when it ends first")
    p.add_argument("--render-minutes", type=float, default=1e9, help="stop rendering further worlds after this long "
                   "(train on those rendered; at least one)")
    args = p.parse_args()
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    render_device = args.render_device or args.device
    torch.set_num_threads(args.threads)
    out, cache = Path(args.out), Path(args.cache)
    out.mkdir(parents=True, exist_ok=True)
    size = (args.height, args.width)
    scenarios = args.scenarios.split(",")
    skips = [int(s) for s in args.frame_skips.split(",")]
    speed = None if args.speed == "none" else tuple(float(v) for v in args.speed.split(","))
    seeds = list(range(args.first_seed, args.first_seed + args.worlds))
    check_training_seeds(seeds, "--first-seed/--worlds")
    t0 = time.time()

    def log(**kw: object) -> None:
        print(json.dumps({"minutes": round((time.time() - t0) / 60, 2), **kw}), flush=True)

    net = FlowNet(args.variant).to(args.device)
    if args.channels_last:
        net = net.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    step = 0
    last = out / "last.pt"
    if last.is_file():
        state = torch.load(last, map_location=args.device)
        net.load_state_dict(state["net"])
        opt.load_state_dict(state["opt"])
        step = int(state["step"])
        log(resumed=str(last), step=step)
    elif args.init:
        load_weights(net, args.init, f"flow network FlowNet({args.variant!r})", "--init")
        log(init=args.init)
    gen = torch.Generator().manual_seed(1234 + step)

    worlds = []
    for s in seeds:
        if worlds and time.time() - t0 > 60 * args.render_minutes:
            log(render_budget_spent=True, worlds=len(worlds))
            break
        sc = scenarios[s % len(scenarios)]
        worlds.append(render_world(s, sc, speed, args.frames, skips, size, args.render_scale, args.max_flow, cache,
                                   exposure=s % 2 == 1, noise=0.02 * ((s * 7919) % 11) / 10, device=render_device))
        log(rendered=f"{sc} seed {s}", pairs=len(worlds[-1]["pairs"]))
    data = SyntheticPairs(worlds, args.device)
    evals = eval_sets(scenarios, cache, device=render_device)
    kitti = kitti_pairs(Path(args.kitti_raw), size, skips) if args.mix_steps > 0 else None
    if kitti is not None:
        kitti = (kitti[0].to(args.device), torch.tensor(kitti[1], device=args.device))
    log(train_pairs=len(data.index), kitti_pairs=0 if kitti is None else len(kitti[1]))
    if step == 0:
        log(step=0, eval=evaluate(net, evals, size))

    def save() -> None:
        torch.save({"net": net.state_dict(), "opt": opt.state_dict(), "step": step, "args": vars(args)},
                   last.with_suffix(".tmp"))
        last.with_suffix(".tmp").replace(last)
        save_weights(net, out / "weights.safetensors",
                     {"task": "flow", "variant": args.variant, "height": args.height, "width": args.width,
                      "global_step": step, "source": str(last)})

    stop = {"flag": False}
    signal.signal(signal.SIGTERM, lambda *_: stop.update(flag=True))
    total = args.sup_steps + args.mix_steps
    net.train()
    deadline = t0 + 60 * args.max_minutes
    train_start, step0 = time.time(), step
    amp = torch.autocast(torch.device(args.device).type, dtype=torch.bfloat16, enabled=args.amp == "bf16")

    def progress() -> float:
        """Share of the run done: by steps, or by the time budget when that comes first."""
        by_time = (time.time() - train_start) / max(deadline - train_start, 1e-9) * (total - step0) + step0
        return max(step, by_time)

    while step < total and not stop["flag"] and time.time() < deadline:
        at = progress()
        mixing = at >= args.sup_steps
        phase_start, phase_len = (args.sup_steps, args.mix_steps) if mixing else (0, args.sup_steps)
        lr = (args.mix_lr if mixing else args.lr) * (0.1 if at - phase_start >= 0.75 * phase_len else 1.0)
        for group in opt.param_groups:
            group["lr"] = lr
        i1, i2, ff, fb, vf, vb = augment(*data.batch(args.batch, gen), gen=gen, gray_prob=args.gray_prob)
        with amp:
            flows_f, flows_b = net.forward_backward(i1, i2, all_scales=True)
        flows_f, flows_b = [f.float() for f in flows_f], [f.float() for f in flows_b]
        loss_f, epe_f = multiscale_epe(flows_f, ff, vf)
        loss_b, _ = multiscale_epe(flows_b, fb, vb)
        loss = 0.5 * (loss_f + loss_b)
        terms = {"epe": round(float(epe_f[0].detach()), 3)}
        if mixing and kitti is not None:
            frames, pairs = kitti
            pick = torch.randint(len(pairs), (args.kitti_batch,), generator=gen).to(pairs.device)
            k1, k2 = frames[pairs[pick, 0]].float(), frames[pairs[pick, 1]].float()
            if torch.rand((), generator=gen) < 0.5:
                k1, k2 = k1.flip(-1), k2.flip(-1)
            with amp:
                kf, kb = net.forward_backward(k1, k2, all_scales=True)
            self_loss, _ = self_supervised_flow_loss(k1, k2, [f.float() for f in kf], [f.float() for f in kb])
            loss = loss + args.self_weight * self_loss
            terms["self"] = round(float(self_loss.detach()), 4)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
        step += 1
        if not math.isfinite(float(loss.detach())):
            raise SystemExit(f"step {step}: loss is {float(loss.detach())}; stopping (last.pt holds the last good "
                             "save)")
        if step % args.log_every == 0:
            log(step=step, phase="mix" if mixing else "sup", lr=lr, loss=round(float(loss.detach()), 4), **terms)
        if step % args.save_every == 0:
            save()
        if step % args.eval_every == 0 or step == total:
            log(step=step, eval=evaluate(net, evals, size))
    save()
    log(step=step, done=step >= total, weights=str(out / "weights.safetensors"))


if __name__ == "__main__":
    main()
