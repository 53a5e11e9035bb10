"""Procedural textures of the synthetic worlds (street and highway), evaluated on 3-D surface coordinates.

Every colour is a function of the hit point on its surface (the box-local point, the world point for the
ground, the world ray direction for the sky) and of a fixed world light, never of the viewpoint, so a
surface point has the same colour in every frame and in both stereo cameras (Lambertian, brightness
constancy holds exactly up to pixel sampling).

Detail that would alias (features smaller than a few pixels at the hit's distance) fades to its mean:
``footprint`` is the metres-per-pixel size of the hit on the surface, and noise octaves or line patterns
finer than ~3 footprints are replaced by their average (a cheap band limit).

All functions take and return tensors on one device (CPU or GPU); constants follow the inputs' device.
This module is pure texture maths: which surface gets which material is :mod:`dfvo.synthetic.shading`.
"""

from __future__ import annotations

import torch


def _noise_table(size: int = 256, seed: int = 1234) -> torch.Tensor:
    """(1,1,size+1,size+1) uniform random lattice values, periodic (last row/column repeat the first)."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.rand(size, size, generator=gen)
    t = torch.cat([t, t[:1]], 0)
    t = torch.cat([t, t[:, :1]], 1)
    return t[None, None]


_TABLE = _noise_table()
_TABLES: dict[str, torch.Tensor] = {"cpu": _TABLE}
_PERIOD = 256.0


def _table(device: torch.device) -> torch.Tensor:
    """The noise lattice on ``device`` (copied once per device)."""
    key = str(device)
    if key not in _TABLES:
        _TABLES[key] = _TABLE.to(device)
    return _TABLES[key]


def _const(values: list[float], like: torch.Tensor) -> torch.Tensor:
    """A small float constant tensor on the device of ``like``."""
    return torch.tensor(values, dtype=torch.float32, device=like.device)


def seed_offset(seed: torch.Tensor | int) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer lattice offsets (x, y) in [0, 256) that make surfaces with different seeds look different."""
    s = torch.as_tensor(seed).to(torch.float64)
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
    return torch.nn.functional.grid_sample(_table(x.device), grid, mode="bilinear",
                                           align_corners=True).reshape(x.shape)


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
        dist = torch.as_tensor(dist, device=footprint.device)
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
    horizon = _const([0.80, 0.86, 0.93], d)
    zenith = _const([0.30, 0.50, 0.85], d)
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


def grass(x: torch.Tensor, z: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) roadside verge and fields at world (x, z): green to straw patches, tufts down to decimetres."""
    big = fbm(x, z, 23, 40.0, 3, fp)
    n = fbm(x, z, 29, 3.0, 6, fp)
    dry = ((big - 0.35) * 2.5).clamp(0, 1)[:, None]
    green = _const([0.30, 0.42, 0.18], x)
    straw = _const([0.58, 0.54, 0.33], x)
    return (green * (1 - dry) + straw * dry) * (0.6 + 0.8 * n)[:, None]


def terrain(u: torch.Tensor, v: torch.Tensor, seed: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) distant hill side on surface coordinates (u, v) in metres: fields, forest patches and tree clumps."""
    field = cell_random(torch.floor(u / 60.0), torch.floor(v / 45.0), seed)
    forest = ((fbm(u, v, seed + 3, 50.0, 2, fp) - 0.45) * 4.0).clamp(0, 1)
    clumps = fbm(u, v, seed + 7, 6.0, 5, fp)
    light = torch.stack([0.42 + 0.25 * field, 0.50 + 0.12 * field, 0.24 + 0.05 * field], -1)
    dark = _const([0.16, 0.26, 0.12], u)
    base = light * (1 - forest)[:, None] + dark * forest[:, None]
    return base * (0.55 + 0.9 * clumps)[:, None]


def foliage(u: torch.Tensor, v: torch.Tensor, seed: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) tree crowns and hedges: dark green leaf clumps with lit and shaded spots."""
    n = fbm(u, v, seed, 1.2, 5, fp)
    tint = cell_random(seed.float() * 0, seed.float() * 0 + 1, seed)
    base = torch.stack([0.14 + 0.12 * tint, 0.27 + 0.10 * tint, 0.10 + 0.04 * tint], -1)
    return base * (0.45 + 1.1 * n)[:, None]


def concrete(h: torch.Tensor, y_up: torch.Tensor, seed: torch.Tensor, joint: float, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) concrete (median barriers, noise walls): grey with stains and a vertical joint every ``joint`` m."""
    n = fbm(h, y_up, seed, 2.0, 5, fp)
    stain = fbm(h * 0.3, y_up, seed + 1, 4.0, 2, fp)
    j = lines(h, joint, 0.04, fp)
    g = (0.55 + 0.35 * (n - 0.5)) * (0.8 + 0.4 * stain) * (1 - 0.5 * j)
    return g[:, None] * _const([1.0, 0.99, 0.95], h)


def guard_rail(h: torch.Tensor, y_up: torch.Tensor, height: torch.Tensor, seed: torch.Tensor,
               fp: torch.Tensor) -> torch.Tensor:
    """(S,3) guard rail seen from the side: a galvanised W-beam on top, posts every 2 m in the dark gap below."""
    beam = band(y_up, height - 0.33, height, fp)
    ridges = lines(y_up - (height - 0.33), 0.11, 0.035, fp)
    n = fbm(h, y_up, seed, 1.0, 4, fp)
    metal = (0.62 + 0.2 * n) * (1 - 0.35 * ridges)
    post = band((torch.remainder(h, 2.0) - 1.0).abs(), -1.0, 0.08, fp)
    lower = 0.12 + 0.33 * post
    g = beam * metal + (1 - beam) * lower
    return g[:, None] * _const([0.97, 0.99, 1.02], h)


def sign_panel(h: torch.Tensor, y_up: torch.Tensor, width: torch.Tensor, height: torch.Tensor, color: torch.Tensor,
               seed: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """(S,3) road sign: coloured panel, white border, rows of white "lettering" blocks."""
    border = 1 - band(h, 0.12, width - 0.12, fp) * band(y_up, 0.12, height - 0.12, fp)
    row = torch.floor(y_up / 0.45)
    col = torch.floor(h / 0.28)
    on = (cell_random(col, row, seed) > 0.45).float()
    glyph = on * band(torch.remainder(y_up, 0.45), 0.12, 0.36, fp) * band(torch.remainder(h, 0.28), 0.03, 0.24, fp)
    glyph = glyph * band(h, 0.35, width - 0.35, fp) * band(y_up, 0.3, height - 0.3, fp)
    white = torch.maximum(border, glyph)[:, None]
    return color * (1 - white) + 0.92 * white


def printed(h: torch.Tensor, y_up: torch.Tensor, color: torch.Tensor, seed: torch.Tensor,
            fp: torch.Tensor) -> torch.Tensor:
    """(S,3) printed matter seen from close by (posters, book covers, papers on a desk), on surface coordinates
    (h, y_up) in metres: a tinted paper with blotches down to millimetres and rows of dark "lettering" blocks
    (2 cm lines, 1.2 cm characters) in some cells of a 12 cm grid."""
    n = fbm(h, y_up, seed, 0.15, 7, fp)
    cell = cell_random(torch.floor(h / 0.12), torch.floor(y_up / 0.12), seed)
    text = (cell > 0.5).float()
    glyph = (cell_random(torch.floor(h / 0.012), torch.floor(y_up / 0.02), seed + 5) > 0.45).float()
    ink = text * glyph * band(torch.remainder(y_up, 0.02), 0.004, 0.016, fp) \
        * band(torch.remainder(h, 0.012), 0.002, 0.010, fp)
    paper = color * (0.55 + 0.9 * (n - 0.5))[:, None]
    return paper * (1 - 0.8 * ink)[:, None]
