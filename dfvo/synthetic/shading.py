"""Shading of cast synthetic views: which material each hit gets, its surface coordinates, normal and lighting.

Convention:
    Views are :class:`~dfvo.synthetic.render.View` of one :class:`~dfvo.synthetic.scene.Scene`; ids
    -1 sky, 0 ground (coloured by ``Scene.ground``), ``1 + m`` object ``m``. A box hit gets the normal of the
    face it lies on and (h, y_up) coordinates on that face (h along the face from its left edge, y_up above
    the box bottom); an ellipsoid hit gets the ellipsoid normal and (azimuth, elevation) arc coordinates in
    metres. Lighting is Lambertian under a fixed sun, so a surface point has one colour in every view; with
    ``shadows`` the objects cast shadows too (still one colour per point and frame in every view).
"""

from __future__ import annotations

import math

import torch

from dfvo.synthetic.render import View, sun_shadowed, yaw_rotate
from dfvo.synthetic.scene import (
    KIND_BARRIER,
    KIND_BUILDING,
    KIND_CAR,
    KIND_FOLIAGE,
    KIND_PAVEMENT,
    KIND_POLE,
    KIND_PRINT,
    KIND_RAIL,
    KIND_SIGN,
    KIND_TERRAIN,
    KIND_WALL,
    SHAPE_ELLIPSOID,
    Scene,
)
from dfvo.synthetic.textures import (
    car,
    concrete,
    facade,
    fbm,
    foliage,
    guard_rail,
    pavement,
    printed,
    sign_panel,
    sky,
    terrain,
)

LIGHT = torch.tensor([-0.35, -0.8, 0.45]) / math.sqrt(0.35**2 + 0.8**2 + 0.45**2)  # towards the sun, y down


def take(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Rows ``x[index]`` for a 1-D int64 ``index`` (``index_select``, much faster than advanced indexing)."""
    return x.index_select(0, index)


def lambert(normal_w: torch.Tensor, sunlit: torch.Tensor | None = None) -> torch.Tensor:
    """(S,) shading factor of world normals (S,3) under the fixed sun: ambient 0.55 plus 0.45 diffuse, the diffuse
    term only where ``sunlit`` (S,) bool (None: everywhere, no cast shadows)."""
    diffuse = (normal_w @ LIGHT.to(normal_w.device)).clamp_min(0)
    if sunlit is not None:
        diffuse = diffuse * sunlit
    return 0.55 + 0.45 * diffuse


def shade_view(scene: Scene, view: View, shadows: bool = False) -> torch.Tensor:
    """(3,H,W) colour image of one cast view; see :func:`shade_views`."""
    return shade_views(scene, [view], shadows)[0]


def _sunlit(scene: Scene, views: list[View], sel: torch.Tensor, n: int) -> torch.Tensor:
    """(S,) bool: the hits ``sel`` (flat indices into the stacked views of ``n`` pixels each) not in a cast shadow."""
    lit = torch.ones(len(sel), dtype=torch.bool, device=sel.device)
    which = torch.div(sel, n, rounding_mode="floor")
    for i, view in enumerate(views):
        rows = _pick(which == i)
        if len(rows):
            lit[rows] = ~sun_shadowed(scene, view, take(sel, rows) - i * n, LIGHT)
    return lit


def _pick(mask: torch.Tensor) -> torch.Tensor:
    return torch.nonzero(mask).squeeze(1)


def shade_views(scene: Scene, views: list[View], shadows: bool = False) -> list[torch.Tensor]:
    """Colour images (3,H,W) in [0,1] of cast views of the same size and intrinsics, shaded in one pass.

    Args:
        scene: the :class:`~dfvo.synthetic.scene.Scene` that was cast.
        views: cast views (depth, ids, pose, world rays), e.g. the left and right camera of a frame.
        shadows: cast the objects' shadows (:func:`~dfvo.synthetic.render.sun_shadowed`): a point that does not
            see the sun keeps the ambient light alone, as a face turned from it does. Off: every point sees it.

    Returns:
        One (3,H,W) float32 image per view, on the views' device.
    """
    H, W = views[0].depth.shape
    n = H * W
    ids = torch.cat([v.ids.reshape(-1) for v in views])
    dev = ids.device
    depth = torch.cat([v.depth.reshape(-1) for v in views])
    dirs = torch.cat([v.rays_w for v in views])
    view_of = torch.arange(len(views), device=dev).repeat_interleave(n)
    origin = torch.stack([torch.from_numpy(v.T_w_c[:3, 3]).float() for v in views]).to(dev)
    fx = float(views[0].K[0, 0])
    img = torch.zeros(len(views) * n, 3, device=dev)
    sel = _pick(ids < 0)
    if len(sel):
        img.index_copy_(0, sel, sky(take(dirs, sel)))
    sel = _pick(ids == 0)
    if len(sel):
        d = take(dirs, sel)
        t = take(depth, sel)
        o = take(origin, take(view_of, sel))
        x = o[:, 0] + t * d[:, 0]
        z = o[:, 2] + t * d[:, 2]
        dn = d.norm(dim=-1)
        cos = (d[:, 1].abs() / dn).clamp_min(0.08)
        fp = t * dn / (fx * cos)
        col = scene.ground(x, z, fp)
        lit = _sunlit(scene, views, sel, n) if shadows else None
        img.index_copy_(0, sel, col * lambert(torch.tensor([[0.0, -1.0, 0.0]], device=dev), lit)[:, None])
    sel = _pick(ids > 0)
    if len(sel):
        lit = _sunlit(scene, views, sel, n) if shadows else None
        img.index_copy_(0, sel, _shade_objects(scene, views, sel, ids, depth, dirs, view_of, fx, lit))
    img = img.clamp(0, 1)
    return [img[i * n:(i + 1) * n].T.reshape(3, H, W) for i in range(len(views))]


def _shade_objects(scene: Scene, views: list[View], sel: torch.Tensor, ids: torch.Tensor, depth: torch.Tensor,
                   dirs: torch.Tensor, view_of: torch.Tensor, fx: float, sunlit: torch.Tensor | None = None
                   ) -> torch.Tensor:
    """(S,3) lit colours of the object hits ``sel`` (flat indices into the stacked views); ``sunlit`` (S,) bool: which
    see the sun (None: all)."""
    dev = ids.device
    m = take(ids, sel) - 1
    vs = take(view_of, sel)
    flat = vs * len(scene.half) + m  # (view, box) -> row of the views' stacked box tables
    box_cos = take(torch.cat([v.box_cos for v in views]), flat)
    box_sin = take(torch.cat([v.box_sin for v in views]), flat)
    box_o = take(torch.cat([v.box_o for v in views]), flat)
    d = take(dirs, sel)
    ds = take(depth, sel)
    p = yaw_rotate(d * ds[:, None], box_cos, box_sin, inverse=True) + box_o  # object-local hit points
    half = take(torch.from_numpy(scene.half).float().to(dev), m)
    axis = (p.abs() / half).argmax(-1)
    sgn = torch.sign(p.gather(1, axis[:, None]).squeeze(1))
    n_loc = torch.nn.functional.one_hot(axis, 3).float() * sgn[:, None]
    shape = take(torch.from_numpy(scene.shape).to(dev), m)
    ell = _pick(shape == SHAPE_ELLIPSOID)
    if len(ell):  # ellipsoid normal: gradient of |p / half|^2
        g = take(p, ell) / take(half, ell) ** 2
        n_loc.index_copy_(0, ell, g / g.norm(dim=-1, keepdim=True))
    n_w = yaw_rotate(n_loc, box_cos, box_sin)
    dn = d.norm(dim=-1)
    cos = ((n_w * d).sum(-1).abs() / dn).clamp_min(0.15)
    fp = ds * dn / (fx * cos)
    kind = take(torch.from_numpy(scene.kind).to(dev), m)
    color = take(torch.from_numpy(scene.color).float().to(dev), m)
    seed = take(torch.from_numpy(scene.seed).to(dev), m)
    y_up = half[:, 1] - p[:, 1]
    # horizontal coordinate on side faces: along z for x-faces, along x for z-faces
    side_x = axis == 0
    h = torch.where(side_x, p[:, 2] + half[:, 2], p[:, 0] + half[:, 0])
    width = torch.where(side_x, 2 * half[:, 2], 2 * half[:, 0])
    top = axis == 1
    col = torch.empty(len(sel), 3, device=dev)

    def put(mask: torch.Tensor, fn) -> None:
        k = _pick(mask)
        if len(k):
            col.index_copy_(0, k, fn(k))

    box = shape != SHAPE_ELLIPSOID
    put((kind == KIND_BUILDING) & ~top, lambda k: facade(
        take(h, k), take(y_up, k), take(width, k), 2 * take(half, k)[:, 1], take(color, k), take(seed, k),
        take(fp, k)))
    put((kind == KIND_BUILDING) & top, lambda k: (0.25 + 0.3 * fbm(
        take(p, k)[:, 0], take(p, k)[:, 2], take(seed, k), 3.0, 3, take(fp, k)))[:, None]
        * torch.tensor([1.0, 0.95, 0.9], device=dev))
    put(kind == KIND_PAVEMENT, lambda k: pavement(
        take(p, k)[:, 0] + take(half, k)[:, 0], take(p, k)[:, 2] + take(half, k)[:, 2], take(color, k),
        take(seed, k), take(fp, k)))
    put(kind == KIND_POLE, lambda k: take(color, k) * (0.7 + 0.6 * fbm(
        take(h, k) * 4.0, take(y_up, k), take(seed, k), 0.8, 3, take(fp, k)))[:, None])
    put(kind == KIND_CAR, lambda k: car(
        take(h, k), take(y_up, k), take(width, k), 2 * take(half, k)[:, 1], take(side_x, k).float(),
        take(color, k), take(seed, k), take(fp, k)))
    put((kind == KIND_BARRIER) | (kind == KIND_WALL), lambda k: take(color, k) * concrete(
        torch.where(take(top, k), take(p, k)[:, 2], take(h, k)), take(y_up, k), take(seed, k),
        6.0, take(fp, k)))
    put((kind == KIND_RAIL) & ~top & box, lambda k: guard_rail(
        take(h, k), take(y_up, k), 2 * take(half, k)[:, 1], take(seed, k), take(fp, k)))
    put((kind == KIND_RAIL) & top, lambda k: torch.full((len(k), 3), 0.6, device=dev))
    put((kind == KIND_SIGN) & (axis == 2), lambda k: sign_panel(
        take(h, k), take(y_up, k), take(width, k), 2 * take(half, k)[:, 1], take(color, k), take(seed, k),
        take(fp, k)))
    put((kind == KIND_SIGN) & (axis != 2), lambda k: torch.full((len(k), 3), 0.5, device=dev))
    put((kind == KIND_PRINT) & ~top, lambda k: printed(take(h, k), take(y_up, k), take(color, k), take(seed, k),
                                                       take(fp, k)))
    put((kind == KIND_PRINT) & top, lambda k: printed(take(p, k)[:, 0], take(p, k)[:, 2], take(color, k),
                                                      take(seed, k) + 1, take(fp, k)))
    if len(ell):
        # arc coordinates on the ellipsoid: azimuth about its vertical axis, elevation, both in metres
        pe, he = take(p, ell), take(half, ell)
        r_mean = 0.5 * (he[:, 0] + he[:, 2])
        u = torch.atan2(pe[:, 0] / he[:, 0], pe[:, 2] / he[:, 2]) * r_mean
        v = torch.asin((-pe[:, 1] / he[:, 1]).clamp(-1, 1)) * 0.5 * (he[:, 1] + r_mean)
        ke, se, fe = take(kind, ell), take(seed, ell), take(fp, ell)
        out = torch.empty(len(ell), 3, device=dev)
        for kd, fn in ((KIND_TERRAIN, terrain), (KIND_FOLIAGE, foliage)):
            k = _pick(ke == kd)
            if len(k):
                out.index_copy_(0, k, fn(take(u, k), take(v, k), take(se, k), take(fe, k)))
        col.index_copy_(0, ell, out)
    return col * lambert(n_w, sunlit)[:, None]
