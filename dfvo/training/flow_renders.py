"""The synthetic render cache of flow training (``data=flow_mix``): every training world's frames and frame-skip pairs
with their exact flows, rendered once at the working size and resized the way inference resizes, kept on disk.

A training world (``SyntheticWorld(seed, scenario, speed)``) is rendered at the working size ``render_scale x`` the
network's input size (640x192 for the 320x96 network), then

    - images (F,3,h,w) are resized to the network size with antialiased bilinear interpolation, as
      :class:`dfvo.sources.networks.NetworkFlow` resizes its inputs;
    - for every gap s of ``frame_skips`` and every frame k, the exact flows k -> k+s and k+s -> k and their validity are
      block-averaged over the valid pixels of each ``render_scale x render_scale`` block (in pixels of the small
      image), valid where the whole block is; pairs without a visible pixel, or whose largest true flow exceeds
      ``max_flow`` pixels of the working size, are dropped.
    - ``sensor_variation``: odd seeds vary their exposure between frames, and seed s has sensor noise of standard
      deviation ``0.02 * ((7919 s) mod 11) / 10`` (0 .. 0.02).

Each world is one file ``CACHE/<tag>.pt``, the tag naming everything the render depends on:
``{scenario}_s{seed}_{frames}f_{h}x{w}x{scale}_sp{speed}_k{skips}_mf{max_flow}`` (``_plain`` appended without sensor
variation). A file records :data:`RENDER_FORMAT`; a file of another format (for example one written by the
retired ``benchmarks/flow_training_run.py``, which has none) is refused with one line naming it: delete it and it
is rendered again. Files are written to a temporary name and renamed, so an interrupted render leaves no half file.

The held-out evaluation sets (:func:`heldout_set`) are cached the same way: seeds ``HELD_OUT_SEED + 2, + 3`` of each
scenario (never trained on, and not the benchmarks' 1000/1001), every second pair (k, k+1), at the working size.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from dfvo.sources.networks import resize_images
from dfvo.synthetic import HELD_OUT_SPEED, SyntheticWorld

__all__ = ["RENDER_FORMAT", "RenderCacheError", "WorldRender", "world_tag", "sensor_noise", "downsample_flow",
           "render_world", "cached_world", "heldout_set"]

RENDER_FORMAT = 2  # 1: the list-of-tuples files of benchmarks/flow_training_run.py (no "format" key)


class RenderCacheError(ValueError):
    """A render cache file that cannot be used (another format, unreadable, another world)."""


@dataclass(frozen=True)
class WorldRender:
    """What one training world's render depends on (see the module docstring).

    Attributes:
        seed, scenario: the world. speed: m/frame (None: the scenario's; a pair: drawn per world in the range).
        frames: frames rendered. size: (h, w) the network size. scale: working size / network size.
        skips: the pair gaps. max_flow: largest true flow of a kept pair, working-size pixels (None: no limit).
        sensor_variation: exposure changes (odd seeds) and sensor noise (see :func:`sensor_noise`).
    """

    seed: int
    scenario: str
    speed: float | tuple[float, float] | None
    frames: int
    size: tuple[int, int]
    scale: int
    skips: tuple[int, ...]
    max_flow: float | None
    sensor_variation: bool = True

    @property
    def tag(self) -> str:
        return world_tag(self)


def world_tag(w: WorldRender) -> str:
    """The cache file name (without ``.pt``) of a world render."""
    h, wd = w.size
    mf = "none" if w.max_flow is None else f"{w.max_flow:g}"
    tag = (f"{w.scenario}_s{w.seed}_{w.frames}f_{h}x{wd}x{w.scale}_sp{w.speed}_k{''.join(map(str, w.skips))}"
           f"_mf{mf}")
    return tag if w.sensor_variation else f"{tag}_plain"


def sensor_noise(seed: int) -> float:
    """Sensor noise standard deviation of training world ``seed`` (0 .. 0.02, fixed per seed)."""
    return 0.02 * ((seed * 7919) % 11) / 10


def downsample_flow(flow: torch.Tensor, valid: torch.Tensor, factor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,2,H,W) flow and (N,1,H,W) validity -> 1/``factor`` size: the mean flow of each block's valid pixels, in the
    small image's pixels, and valid where every pixel of the block is."""
    if factor == 1:
        return flow, valid
    v = valid.float()
    s = F.avg_pool2d(flow * v, factor)
    n = F.avg_pool2d(v, factor)
    return s / n.clamp_min(1e-6) / factor, n > 0.999


def render_world(w: WorldRender, device: str = "cpu") -> dict[str, object]:
    """Render one training world (on ``device``) into the cache format (tensors on the CPU).

    Returns:
        ``format``, ``tag``, ``images`` (F,3,h,w) fp16, ``pairs`` (P,2) int64 frame indices (k, k+s), ``flow_fwd``
        (P,2,h,w) fp16 on image k, ``valid_fwd`` (P,1,h,w) bool, ``flow_bwd``/``valid_bwd`` (k+s -> k on image k+s),
        ``scenario``, ``seed``.
    """
    h, wd = w.size
    odd = w.seed % 2 == 1
    world = SyntheticWorld(seed=w.seed, num_frames=w.frames, height=h * w.scale, width=wd * w.scale,
                           scenario=w.scenario, speed=w.speed, exposure_change=w.sensor_variation and odd,
                           noise_std=sensor_noise(w.seed) if w.sensor_variation else 0.0, device=device)
    images = resize_images(torch.stack([world.image(k) for k in range(w.frames)]), (h, wd))
    pairs, flows = [], {"flow_fwd": [], "valid_fwd": [], "flow_bwd": [], "valid_bwd": []}
    for s in w.skips:
        for k in range(w.frames - s):
            fwd, vf = world.flow(k, k + s)
            if not bool(vf.any()):
                continue
            if w.max_flow is not None and float(fwd.norm(dim=0)[vf[0]].max()) > w.max_flow:
                continue
            bwd, vb = world.flow(k + s, k)
            ff, vff = downsample_flow(fwd[None], vf[None], w.scale)
            fb, vfb = downsample_flow(bwd[None], vb[None], w.scale)
            pairs.append((k, k + s))
            for key, x in (("flow_fwd", ff[0].half()), ("valid_fwd", vff[0]), ("flow_bwd", fb[0].half()),
                           ("valid_bwd", vfb[0])):
                flows[key].append(x.cpu())
    if not pairs:
        raise RenderCacheError(f"training world {w.tag}: no frame pair within max_flow={w.max_flow} px; raise "
                               "data.max_flow or lower data.speed (a driving world's; a hand-held world moves at "
                               "its own pace)")
    out: dict[str, object] = {"format": RENDER_FORMAT, "tag": w.tag, "images": images.half().cpu(),
                              "pairs": torch.tensor(pairs, dtype=torch.int64), "scenario": w.scenario,
                              "seed": w.seed}
    out.update({key: torch.stack(v) for key, v in flows.items()})
    return out


def _save(obj: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    tmp.replace(path)


def _load(path: Path, tag: str) -> dict:
    """A cache file, checked: readable, of :data:`RENDER_FORMAT`, holding ``tag``."""
    delete = "delete it (it is rendered again) or point data.cache_dir to another folder"
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unpickling, truncated zip, ...: all mean "unusable"
        reason = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
        raise RenderCacheError(f"render cache file {path} cannot be read ({type(err).__name__}: {reason}); "
                               f"{delete}") from err
    found = obj.get("format") if isinstance(obj, dict) else None
    if found != RENDER_FORMAT:
        origin = "none recorded: written by the retired benchmarks/flow_training_run.py" if found is None else found
        raise RenderCacheError(f"render cache file {path} was written in another format ({origin}); this dfvo "
                               f"reads format {RENDER_FORMAT}: {delete}")
    if obj.get("tag") != tag:
        raise RenderCacheError(f"render cache file {path} holds {obj.get('tag')!r}, expected {tag!r}; {delete}")
    return obj


def cached_world(w: WorldRender, cache_dir: str | Path | None, device: str = "cpu") -> dict:
    """The render of ``w`` from ``cache_dir`` (rendered and written there when missing; None: no cache).

    Raises:
        RenderCacheError: a cache file of another format, another world, or unreadable (one line naming it).
    """
    if cache_dir is None:
        return render_world(w, device)
    path = Path(cache_dir) / f"{w.tag}.pt"
    if path.is_file():
        return _load(path, w.tag)
    out = render_world(w, device)
    _save(out, path)
    return out


def heldout_set(scenario: str, seeds: Sequence[int], frames: int, size: tuple[int, int], every: int,
                cache_dir: str | Path | None, device: str = "cpu") -> dict:
    """Held-out pairs (k, k+1), k = 0, every, 2*every, ... of the worlds ``seeds`` of ``scenario`` at the working
    size ``size`` (h, w) (speed: :data:`dfvo.synthetic.HELD_OUT_SPEED`), cached like the training worlds.

    Returns:
        ``format``, ``tag``, ``name`` (the scenario), ``image``, ``image_next`` (N,3,H,W) float32, ``flow`` (N,2,H,W),
        ``valid`` (N,1,H,W) bool: the true forward flow and its validity.
    """
    h, w = size
    tag = f"heldout_{scenario}_s{'-'.join(map(str, seeds))}_{frames}f_{h}x{w}_every{every}"
    path = Path(cache_dir) / f"{tag}.pt" if cache_dir is not None else None
    if path is not None and path.is_file():
        return _load(path, tag)
    rows = []
    for seed in seeds:
        world = SyntheticWorld(seed=int(seed), num_frames=frames, height=h, width=w, scenario=scenario,
                               speed=HELD_OUT_SPEED.get(scenario), device=device)
        for k in range(0, frames - 1, every):
            flow, valid = world.flow(k, k + 1)
            rows.append(tuple(x.cpu() for x in (world.image(k), world.image(k + 1), flow, valid)))
    out: dict[str, object] = {"format": RENDER_FORMAT, "tag": tag, "name": scenario}
    out.update({key: torch.stack(col) for key, col in zip(("image", "image_next", "flow", "valid"), zip(*rows))})
    if path is not None:
        _save(out, path)
    return out
