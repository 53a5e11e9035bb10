"""Procedural textures of the synthetic street, evaluated on 3-D surface coordinates.

Every colour is a function of the hit point on its surface (the box-local point, the world point for the
ground, the world ray direction for the sky) and of a fixed world light, never of the viewpoint, so a
surface point has the same colour in every frame and in both stereo cameras (Lambertian, brightness
constancy holds exactly up to pixel sampling).

Detail that would alias (features smaller than a few pixels at the hit's distance) fades to its mean:
``footprint`` is the metres-per-pixel size of the hit on the surface, and noise octaves or line patterns
finer than ~3 footprints are replaced by their average (a cheap band limit).
"""

from __future__ import annotations

import math

import torch

from dfvo.data.synthetic_render import View, yaw_rotate
from dfvo.data.synthetic_scene import KIND_BUILDING, KIND_CAR, KIND_PAVEMENT, KIND_POLE, ROAD_HALF_WIDTH, Scene

LIGHT = torch.tensor([-0.35, -0.8, 0.45]) / math.sqrt(0.35**2 + 0.8**2 + 0.45**2)  # towards the sun, y down


def _noise_table(size: int = 256, seed: int = 1234) -> torch.Tensor:
    """(1,1,size+1,size+1) uniform random lattice values, periodic (last row/column repeat the first)."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.rand(size, size, generator=gen)
    t = torch.cat([t, t[:1]], 0)
    t = torch.cat([t, t[:, :1]], 1)
    return t[None, None]


_TABLE = _noise_table()
_PERIOD = 256.0


def seed_offset(seed: torch.Tensor | int) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer lattice offsets (x, y) in [0, 256) that make surfaces with different seeds look different."""
    s = torch.as_tensor(seed, dtype=torch.float64)
    ox = torch.floor(torch.frac(s * 0.7548776662) * _PERIOD).float()
    oy = torch.floor(torch.frac(s * 0.5698402910) * _PERIOD).float()
    return ox, oy


def lattice(x: torch.Tensor, y: torch.Tensor, seed: torch.Tensor | int, k: int = 0,
            offset: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Value noise in [0,1] with unit lattice spacing (bilinear between random lattice values, period 256).

    At integer (x, y) it returns a lattice value itself: a uniform random number per cell. ``k`` selects an
    independent layer; ``offset`` may pass a precomputed ``seed_offset(seed)``.
    """
    ox, oy = seed_offset(seed) if offset is None else offset
    gx = torch.remainder(x + (ox + 37.0 * k), _PERIOD) * (2.0 / _PERIOD) - 1.0
    gy = torch.remainder(y + (oy + 91.0 * k), _PERIOD) * (2.0 / _PERIOD) - 1.0
    grid = torch.stack([gx, gy], -1).reshape(1, 1, -1, 2)
    return torch.nn.functional.grid_sample(_TABLE, grid, mode="bilinear", align_corners=True).reshape(x.shape)


def cell_random(ix: torch.Tensor, iy: torch.Tensor, seed: torch.Tensor | int) -> torch.Tensor:
    """Uniform [0,1) value per integer cell (ix, iy) (float tensors holding integers), deterministic."""
    return lattice(ix, iy, seed, k=7)


def fbm(x: torch.Tensor, y: torch.Tensor, seed: torch.Tensor | int, wavelength: float, octaves: int,
        footprint: torch.Tensor) -> torch.Tensor:
    """Multi-octave value noise in [0,1] (mean 0.5); octaves finer than ~3 footprints fade to 0.5."""
    total = torch.zeros_like(x)
    norm = 0.0
    amp = 1.0
    lam = wavelength
    offset = seed_offset(seed)
    inv_fp = 1.0 / (3.0 * footprint)
    for o in range(octaves):
        fade = (lam * inv_fp - 1.0).clamp(0.0, 1.0)
        if bool((fade > 0).any()):  # skip octaves that are band-limited away everywhere
            n = lattice(x * (1.0 / lam), y * (1.0 / lam), seed, k=o + 1, offset=offset)
            total = total + amp * (0.5 + (n - 0.5) * fade)
        else:
            total = total + 0.5 * amp
        norm += amp
        amp *= 0.55
        lam *= 0.5
    return total / norm


def lines(c: torch.Tensor, period: float, width: float, footprint: torch.Tensor) -> torch.Tensor:
    """Anti-aliased periodic lines of ``width`` every ``period`` along coordinate ``c`` (1 on a line)."""
    dist = (torch.frac(c / period + 0.5) - 0.5).abs() * period
    if not isinstance(dist, torch.Tensor):
        dist = torch.as_tensor(dist)
    fp = footprint.clamp_min(1e-4)
    m = ((0.5 * width - dist) / fp + 0.5).clamp(0.0, 1.0)
    fade = (period / (4.0 * fp) - 1.0).clamp(0.0, 1.0)
    return m * fade + (width / period) * (1.0 - fade)


def band(c: torch.Tensor, lo: float | torch.Tensor, hi: float | torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
    """Anti-aliased indicator of ``lo <= c <= hi``."""
    fp = footprint.clamp_min(1e-4)
    return ((c - lo) / fp + 0.5).clamp(0, 1) * ((hi - c) / fp + 0.5).clamp(0, 1)


def sky(dirs_w: torch.Tensor) -> torch.Tensor:
    """(S,3) sky colour of world-frame ray directions (S,3): gradient plus soft clouds."""
    d = dirs_w / dirs_w.norm(dim=-1, keepdim=True)
    elev = (-d[:, 1]).clamp(-0.2, 1.0)
    az = torch.atan2(d[:, 0], d[:, 2])
    t = elev.clamp_min(0).sqrt()[:, None]
    horizon = torch.tensor([0.80, 0.86, 0.93])
    zenith = torch.tensor([0.30, 0.50, 0.85])
    base = horizon * (1 - t) + zenith * t
    fp = torch.full_like(az, 1e-3)
    c = fbm(az * 8.0, elev * 20.0, 4242, 1.0, 4, fp)
    cloud = ((c - 0.45) * 3.0).clamp(0, 1)[:, None]
    return base * (1 - 0.8 * cloud) + 0.97 * 0.8 * cloud


def asphalt(x: torch.Tensor, z: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,) grey level of the road surface at world (x, z): patches (metres) down to grain (centimetres)."""
    n = fbm(x, z, 11, 5.0, 7, fp)
    return 0.31 + 0.55 * (n - 0.5)


def facade(h: torch.Tensor, y_up: torch.Tensor, width: torch.Tensor, height: torch.Tensor, color: torch.Tensor,
           seed: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) building wall: bricks with per-brick tint, mortar, grime, and a window grid above the ground floor.

    Args:
        h: horizontal coordinate on the wall from its left edge (m); y_up: height above the wall's base (m).
        width, height: wall size (m); color: (S,3) base colour; seed: (S,) int; fp: footprint (m/pixel).
    """
    row = torch.floor(y_up / 0.3)
    hh = h + 0.3 * torch.remainder(row, 2)
    brick = cell_random(torch.floor(hh / 0.6), row, seed)
    fade = (0.3 / (3.0 * fp) - 1.0).clamp(0, 1)
    tint = 0.85 + 0.3 * (0.5 + (brick - 0.5) * fade)
    mortar = torch.maximum(lines(y_up, 0.3, 0.04, fp), lines(hh, 0.6, 0.04, fp) * band(
        torch.remainder(y_up, 0.3), 0.02, 0.28, fp))
    grime = fbm(h, y_up, seed + 5, 3.0, 3, fp)
    wall = color * (tint * (0.6 + 0.8 * grime))[:, None]
    wall = wall * (1 - mortar[:, None]) + 0.72 * mortar[:, None]
    # windows: per-building spacing from the seed
    px = 2.6 + cell_random(seed.float() * 0, seed.float() * 0, seed) * 1.2
    cell = torch.floor(h / px)
    cx = h - (cell + 0.5) * px
    cy = torch.remainder(y_up, 3.2) - 1.7
    inside = band(cell * px, 0.5, width - px - 0.5, fp) * band(y_up, 3.2, height - 1.0, fp)
    win = band(cx, -0.6, 0.6, fp) * band(cy, -0.8, 0.8, fp) * inside
    frame = band(cx, -0.72, 0.72, fp) * band(cy, -0.92, 0.92, fp) * inside - win
    refl = fbm(h * 0.7, y_up, seed + 17, 2.0, 2, fp)
    glass = torch.stack([0.12 + 0.25 * refl, 0.17 + 0.25 * refl, 0.24 + 0.28 * refl], -1)
    out = wall * (1 - win - frame)[:, None] + glass * win[:, None] + 0.85 * frame[:, None]
    return out


def pavement(a: torch.Tensor, b: torch.Tensor, color: torch.Tensor, seed: torch.Tensor,
             fp: torch.Tensor) -> torch.Tensor:
    """(S,3) square paving slabs (0.5 m) with per-slab tint and joints, on surface coords (a, b)."""
    slab = cell_random(torch.floor(a / 0.5), torch.floor(b / 0.5), seed)
    fade = (0.5 / (3.0 * fp) - 1.0).clamp(0, 1)
    tint = 0.85 + 0.3 * (0.5 + (slab - 0.5) * fade)
    joint = torch.maximum(lines(a, 0.5, 0.03, fp), lines(b, 0.5, 0.03, fp))
    n = fbm(a, b, seed + 3, 1.5, 3, fp)
    g = tint * (0.8 + 0.4 * n) * (1 - 0.45 * joint)
    return color * g[:, None]


def car(h: torch.Tensor, y_up: torch.Tensor, length: torch.Tensor, height: torch.Tensor, side: torch.Tensor,
        color: torch.Tensor, seed: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) vehicle body: paint with noise and panel seams, a dark window band (side faces: ``side`` 1, plus
    the front/rear windscreen), dark wheels zone on the sides."""
    n = fbm(h, y_up, seed, 0.8, 4, fp)
    seams = torch.maximum(lines(h, 0.9, 0.03, fp), lines(y_up, 0.7, 0.03, fp))
    body = color * ((0.7 + 0.6 * n) * (1 - 0.35 * seams))[:, None]
    win = band(y_up, 0.62 * height, 0.92 * height, fp) * band(h, 0.12 * length, 0.88 * length, fp)
    wheel = band(y_up, -1.0, 0.3, fp) * side
    glass = (0.08 + 0.25 * n)[:, None].expand(-1, 3)
    return body * (1 - win - wheel).clamp(0, 1)[:, None] + glass * win[:, None] + 0.06 * wheel[:, None]


def take(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Rows ``x[index]`` for a 1-D int64 ``index`` (``index_select``, much faster than advanced indexing)."""
    return x.index_select(0, index)


def lambert(normal_w: torch.Tensor) -> torch.Tensor:
    """(S,) shading factor of world normals under the fixed sun: ambient 0.55 plus 0.45 diffuse."""
    return 0.55 + 0.45 * (normal_w @ LIGHT).clamp_min(0)


def shade_view(scene: Scene, view: View, rays: torch.Tensor, legs: list) -> torch.Tensor:
    """(3,H,W) colour image of one cast view; see :func:`shade_views`."""
    return shade_views(scene, [view], rays, legs)[0]


def shade_views(scene: Scene, views: list[View], rays: torch.Tensor, legs: list) -> list[torch.Tensor]:
    """Colour images (3,H,W) in [0,1] of cast views of the same size and intrinsics, shaded in one pass.

    Args:
        scene: the :class:`~dfvo.data.synthetic_scene.Scene` that was cast.
        views: cast views (depth, ids, pose), e.g. the left and right camera of a frame.
        rays: (H*W,3) camera rays of the views.
        legs: the route's straight streets (lane markings).
    """
    H, W = views[0].depth.shape
    n = H * W
    ids = torch.cat([v.ids.reshape(-1) for v in views])
    depth = torch.cat([v.depth.reshape(-1) for v in views])
    dirs = torch.cat([v.rays_w for v in views])
    view_of = torch.arange(len(views)).repeat_interleave(n)
    origin = torch.stack([torch.from_numpy(v.T_w_c[:3, 3]).float() for v in views])
    fx = float(views[0].K[0, 0])
    img = torch.zeros(len(views) * n, 3)
    sel = torch.nonzero(ids < 0).squeeze(1)
    if len(sel):
        img.index_copy_(0, sel, sky(take(dirs, sel)))
    sel = torch.nonzero(ids == 0).squeeze(1)
    if len(sel):
        d = take(dirs, sel)
        t = take(depth, sel)
        o = take(origin, take(view_of, sel))
        x = o[:, 0] + t * d[:, 0]
        z = o[:, 2] + t * d[:, 2]
        dn = d.norm(dim=-1)
        cos = (d[:, 1].abs() / dn).clamp_min(0.08)
        fp = t * dn / (fx * cos)
        g = asphalt(x, z, fp)
        mark = torch.zeros_like(g)
        for leg in legs:
            sx, sz = float(leg.start[0]), float(leg.start[1])
            hx, hz = math.sin(leg.theta), math.cos(leg.theta)
            la = (x - sx) * hx + (z - sz) * hz
            lt = (x - sx) * hz - (z - sz) * hx
            lo = ROAD_HALF_WIDTH if leg.turn_in else -1e9
            hi = leg.length - ROAD_HALF_WIDTH if leg.turn_out else 1e9
            inl = band(la, lo, hi, fp)
            centre = band(lt, -0.08, 0.08, fp) * band(torch.remainder(la, 6.0), 0.0, 3.0, fp)
            edge = band(lt.abs(), 3.5, 3.65, fp)
            mark = torch.maximum(mark, inl * torch.maximum(centre, edge))
        g = g * (1 - mark) + 0.82 * mark
        col = g[:, None] * torch.tensor([0.97, 0.98, 1.03])
        img.index_copy_(0, sel, col * lambert(torch.tensor([[0.0, -1.0, 0.0]])))
    sel = torch.nonzero(ids > 0).squeeze(1)
    if len(sel):
        m = take(ids, sel) - 1
        vs = take(view_of, sel)
        flat = vs * len(scene.half) + m  # (view, box) -> row of the views' stacked box tables
        box_cos = take(torch.cat([v.box_cos for v in views]), flat)
        box_sin = take(torch.cat([v.box_sin for v in views]), flat)
        box_o = take(torch.cat([v.box_o for v in views]), flat)
        d = take(dirs, sel)
        ds = take(depth, sel)
        p = yaw_rotate(d * ds[:, None], box_cos, box_sin, inverse=True) + box_o  # box-local hit points
        half = take(torch.from_numpy(scene.half).float(), m)
        axis = (p.abs() / half).argmax(-1)
        sgn = torch.sign(p.gather(1, axis[:, None]).squeeze(1))
        n_loc = torch.nn.functional.one_hot(axis, 3).float() * sgn[:, None]
        n_w = yaw_rotate(n_loc, box_cos, box_sin)
        dn = d.norm(dim=-1)
        cos = ((n_w * d).sum(-1).abs() / dn).clamp_min(0.15)
        fp = ds * dn / (fx * cos)
        kind = take(torch.from_numpy(scene.kind), m)
        color = take(torch.from_numpy(scene.color).float(), m)
        seed = take(torch.from_numpy(scene.seed), m)
        y_up = half[:, 1] - p[:, 1]
        # horizontal coordinate on side faces: along z for x-faces, along x for z-faces
        side_x = axis == 0
        h = torch.where(side_x, p[:, 2] + half[:, 2], p[:, 0] + half[:, 0])
        width = torch.where(side_x, 2 * half[:, 2], 2 * half[:, 0])
        top = axis == 1
        col = torch.empty(len(sel), 3)

        def pick(mask: torch.Tensor) -> torch.Tensor:
            return torch.nonzero(mask).squeeze(1)

        k = pick((kind == KIND_BUILDING) & ~top)
        if len(k):
            hk, yk, wk, halfk, ck, sk, fk = (take(x, k) for x in (h, y_up, width, half, color, seed, fp))
            col.index_copy_(0, k, facade(hk, yk, wk, 2 * halfk[:, 1], ck, sk, fk))
        k = pick((kind == KIND_BUILDING) & top)
        if len(k):
            pk = take(p, k)
            r = fbm(pk[:, 0], pk[:, 2], take(seed, k), 3.0, 3, take(fp, k))
            col.index_copy_(0, k, (0.25 + 0.3 * r)[:, None] * torch.tensor([1.0, 0.95, 0.9]))
        k = pick(kind == KIND_PAVEMENT)
        if len(k):
            pk, halfk = take(p, k), take(half, k)
            col.index_copy_(0, k, pavement(pk[:, 0] + halfk[:, 0], pk[:, 2] + halfk[:, 2], take(color, k),
                                           take(seed, k), take(fp, k)))
        k = pick(kind == KIND_POLE)
        if len(k):
            nz = fbm(take(h, k) * 4.0, take(y_up, k), take(seed, k), 0.8, 3, take(fp, k))
            col.index_copy_(0, k, take(color, k) * (0.7 + 0.6 * nz)[:, None])
        k = pick(kind == KIND_CAR)
        if len(k):
            hk, yk, wk, halfk, ck, sk, fk = (take(x, k) for x in (h, y_up, width, half, color, seed, fp))
            col.index_copy_(0, k, car(hk, yk, wk, 2 * halfk[:, 1], take(side_x, k).float(), ck, sk, fk))
        img.index_copy_(0, sel, col * lambert(n_w)[:, None])
    img = img.clamp(0, 1)
    return [img[i * n:(i + 1) * n].T.reshape(3, H, W) for i in range(len(views))]
