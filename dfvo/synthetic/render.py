"""Vectorised ray casting of the synthetic worlds and exact optical flow between two rendered views.

Convention:
    A view is a pinhole camera with intrinsics ``K`` (3,3) and pose ``T_w_c`` (4,4, float64 numpy). Pixel
    (u, v) has its ray ``d = K^-1 [u, v, 1]`` (camera frame, z-component 1), so the ray parameter of a hit
    *is* its depth z. Per-pixel work is float32 in camera-relative coordinates (box centres are shifted by
    the camera position in float64 first), so positions hundreds of metres from the origin keep
    sub-millimetre precision. Ids: -1 sky, 0 ground, ``1 + m`` object ``m`` of the :class:`Scene`.
    Objects are boxes or ellipsoids (``Scene.shape``) inscribed in their box. Tensors live on the device of
    ``rays`` (CPU or GPU); the few per-object numbers (M of them) are computed in numpy float64 first.

Objects are culled to the screen rectangle their bounding-box corners project to (and to their drawing
distance ``Scene.cull``), binned into 8x8 pixel tiles, and the slab test (boxes) or the quadratic (ellipsoids)
runs on all (object, tile) pairs at once; a scatter-min keeps the nearest hit per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dfvo.synthetic.scene import DRAW_DISTANCE, SHAPE_ELLIPSOID, Scene, rot_y
from dfvo.synthetic.trajectory import CAMERA_HEIGHT

TILE = 8
FAR = DRAW_DISTANCE  # default drawing distance of an object (its nearest possible point), metres
NEAR = 0.05
SKY_DEPTH = 1000.0  # depth value returned for sky pixels (they are at infinity)


@dataclass
class View:
    """One cast view. ``depth`` (H,W) float32 (inf for sky), ``ids`` (H,W) int64, ``T_w_c`` (4,4) float64,
    ``K`` (3,3) float32, ``frame`` its frame index (box poses), ``box_centre``/``box_yaw`` (M,3)/(M,) the box
    poses, ``box_cos``/``box_sin`` (M,) float32 cosine and sine of the yaws, ``box_o`` (M,3) float32 camera
    centre in box coordinates, ``rays_w`` (H*W,3) float32 pixel rays in world axes (camera-relative)."""

    depth: torch.Tensor
    ids: torch.Tensor
    T_w_c: np.ndarray
    K: torch.Tensor
    frame: int
    box_centre: np.ndarray
    box_yaw: np.ndarray
    box_cos: torch.Tensor
    box_sin: torch.Tensor
    box_o: torch.Tensor
    rays_w: torch.Tensor


def yaw_rotate(v: torch.Tensor, c: torch.Tensor, s: torch.Tensor, inverse: bool = False) -> torch.Tensor:
    """Rotate (...,3) vectors by ``R_y(yaw)`` (or its transpose) given (...) cosines and sines of the yaws."""
    x, y, z = v.unbind(-1)
    if inverse:
        return torch.stack([c * x - s * z, y, s * x + c * z], -1)
    return torch.stack([c * x + s * z, y, -s * x + c * z], -1)


def camera_rays(K: torch.Tensor, height: int, width: int, device: torch.device | str | None = None) -> torch.Tensor:
    """(H*W,3) float32 rays ``K^-1 [u, v, 1]`` of all pixel centres, row-major, on ``device`` (default: K's)."""
    K = K.to(device) if device is not None else K
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32, device=K.device),
                          torch.arange(width, dtype=torch.float32, device=K.device), indexing="ij")
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 3)


_EDGES = np.array([[a, b] for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1])


def _screen_rects(corners_c: np.ndarray, K: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel rectangles (M,4) [u0, u1, v0, v1] covered by boxes with camera-frame corners (M,8,3), and a keep mask.

    The box is clipped by the near plane: its projected outline is bounded by the corners in front and the
    points where its 12 edges cross ``z = NEAR``.
    """
    p0 = corners_c[:, _EDGES[:, 0]]
    p1 = corners_c[:, _EDGES[:, 1]]
    z0, z1 = p0[..., 2], p1[..., 2]
    cross = (z0 - NEAR) * (z1 - NEAR) < 0
    f = np.where(cross, (NEAR - z0) / np.where(cross, z1 - z0, 1.0), 0.0)
    pc = p0 + f[..., None] * (p1 - p0)
    pts = np.concatenate([corners_c, pc], 1)
    ok = np.concatenate([corners_c[..., 2] > NEAR, cross], 1)
    zs = np.maximum(pts[..., 2], NEAR)
    u = K[0, 0] * pts[..., 0] / zs + K[0, 2]
    v = K[1, 1] * pts[..., 1] / zs + K[1, 2]
    big = 1e9
    rect = np.stack([np.where(ok, u, big).min(1) - 1, np.where(ok, u, -big).max(1) + 1,
                     np.where(ok, v, big).min(1) - 1, np.where(ok, v, -big).max(1) + 1], 1)
    rect[:, [0, 2]] = np.maximum(rect[:, [0, 2]], 0.0)
    rect[:, 1] = np.minimum(rect[:, 1], W - 1.0)
    rect[:, 3] = np.minimum(rect[:, 3], H - 1.0)
    keep = ok.any(1) & (rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])
    return rect, keep


def _tile_pairs(rect: np.ndarray, H: int, W: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor,
                                                                                torch.Tensor]:
    """All (object, 8x8 tile) pairs covering pixel rectangles (M',4): pair -> object row (P,), flat pixel index
    (P,64) and an in-image mask (P,64)."""
    r = torch.from_numpy(rect).to(device)
    tu0, tu1, tv0, tv1 = (torch.floor(r[:, k] / TILE).long() for k in range(4))
    ncol = tu1 - tu0 + 1
    nt = ncol * (tv1 - tv0 + 1)
    P = int(nt.sum())
    pair = torch.repeat_interleave(torch.arange(len(rect), device=device), nt, output_size=P)
    local = torch.arange(P, device=device) - torch.repeat_interleave(torch.cumsum(nt, 0) - nt, nt, output_size=P)
    nc = ncol.index_select(0, pair)
    tu = tu0.index_select(0, pair) + local % nc
    tv = tv0.index_select(0, pair) + torch.div(local, nc, rounding_mode="floor")
    off = torch.arange(TILE * TILE, device=device)
    pu = tu[:, None] * TILE + (off % TILE)[None]
    pv = tv[:, None] * TILE + torch.div(off, TILE, rounding_mode="floor")[None]
    inside = (pu < W) & (pv < H)
    return pair, pv.clamp(max=H - 1) * W + pu.clamp(max=W - 1), inside


def _slab(o: torch.Tensor, d: tuple[torch.Tensor, ...], hf: torch.Tensor) -> torch.Tensor:
    """Entry ray parameter (P,64) of rays ``o + t d`` (box-local, o (P,3), d 3x(P,64)) into boxes of half sizes
    hf (P,3); inf where missed or behind ``NEAR``."""
    t_near = t_far = None
    for k in range(3):  # slab test, one axis at a time
        inv = 1.0 / d[k]
        t1 = (-hf[:, k:k + 1] - o[:, k:k + 1]) * inv
        t2 = (hf[:, k:k + 1] - o[:, k:k + 1]) * inv
        lo, hi = torch.minimum(t1, t2), torch.maximum(t1, t2)
        t_near = lo if t_near is None else torch.maximum(t_near, lo)
        t_far = hi if t_far is None else torch.minimum(t_far, hi)
    hit = (t_far >= t_near) & (t_near > NEAR)
    return torch.where(hit, t_near, torch.full_like(t_near, float("inf")))


def _ellipsoid(o: torch.Tensor, d: tuple[torch.Tensor, ...], hf: torch.Tensor) -> torch.Tensor:
    """As :func:`_slab` for the ellipsoids inscribed in the boxes (semi-axes hf): the nearer root of
    ``|(o + t d) / hf|^2 = 1`` (scaling the axes keeps the ray parameter)."""
    q = [o[:, k:k + 1] / hf[:, k:k + 1] for k in range(3)]
    e = [d[k] / hf[:, k:k + 1] for k in range(3)]
    a = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    b = q[0] * e[0] + q[1] * e[1] + q[2] * e[2]
    c = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] - 1.0
    disc = b * b - a * c
    t = (-b - disc.clamp_min(0).sqrt()) / a
    return torch.where((disc >= 0) & (t > NEAR), t, torch.full_like(t, float("inf")))


def cast(scene: Scene, frame: int, T_w_c: np.ndarray, K: torch.Tensor, rays: torch.Tensor, height: int,
         width: int) -> View:
    """Ray-cast ground plane and objects for one camera.

    Args:
        scene: the world's objects.
        frame: frame index (poses of the moving boxes).
        T_w_c: (4,4) float64 camera-to-world pose.
        K: (3,3) float32 intrinsics.
        rays: (H*W,3) output of :func:`camera_rays` for ``K``, on the device to render on.
        height, width: image size.

    Returns:
        The :class:`View` with depth (inf where nothing is hit) and ids, on the device of ``rays``.
    """
    H, W = height, width
    dev = rays.device
    R_wc = T_w_c[:3, :3]
    o = T_w_c[:3, 3]
    centre, yaw = scene.box_poses(frame)
    Rb = rot_y(yaw)  # (M,3,3) T_w_o rotations
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners_w = centre[:, None, :] + np.einsum("mij,mkj->mki", Rb, signs[None] * scene.half[:, None, :])
    corners_c = (corners_w - o) @ R_wc
    dist = np.linalg.norm(centre - o, axis=1) - np.linalg.norm(scene.half, axis=1)
    rect, keep = _screen_rects(corners_c, K.detach().cpu().double().numpy(), H, W)
    keep &= dist < scene.cull
    idx = np.nonzero(keep)[0]
    o_all = torch.from_numpy(np.einsum("mji,mj->mi", Rb, o[None] - centre)).float().to(dev)
    cos_all = torch.from_numpy(np.cos(yaw)).float().to(dev)
    sin_all = torch.from_numpy(np.sin(yaw)).float().to(dev)

    # ground plane y_w = CAMERA_HEIGHT, rays in world orientation
    rays_w = rays @ torch.from_numpy(R_wc).float().to(dev).T
    dy = rays_w[:, 1].contiguous()
    t_ground = (CAMERA_HEIGHT - float(o[1])) / dy
    best = torch.where((dy > 1e-6) & (t_ground > 0), t_ground, torch.full_like(dy, float("inf")))
    ids = torch.where(torch.isfinite(best), 0, -1).long()

    if len(idx):
        pair_box, pix, inside = _tile_pairs(rect[idx], H, W, dev)
        # per pair: camera origin in the object's frame, half sizes, and the pixel rays in object axes
        gidx = torch.from_numpy(idx).to(dev).index_select(0, pair_box)
        ol = o_all.index_select(0, gidx)
        hf = torch.from_numpy(scene.half).float().to(dev).index_select(0, gidx)
        c, sn = cos_all.index_select(0, gidx)[:, None], sin_all.index_select(0, gidx)[:, None]
        flat_pix = pix.reshape(-1)
        rw = rays_w.T.contiguous()
        dxw, dyw, dzw = (rw[k].index_select(0, flat_pix).view(pix.shape) for k in range(3))
        d = (c * dxw - sn * dzw, dyw, sn * dxw + c * dzw)  # ray in box axes (R_y^T d)
        ell = scene.shape[idx] == SHAPE_ELLIPSOID
        if not ell.any():
            t = _slab(ol, d, hf)
        else:
            is_ell = torch.from_numpy(ell).to(dev).index_select(0, pair_box)
            t = torch.full_like(d[0], float("inf"))
            for rows, fn in ((torch.nonzero(~is_ell).squeeze(1), _slab),
                             (torch.nonzero(is_ell).squeeze(1), _ellipsoid)):
                if len(rows):
                    t.index_copy_(0, rows, fn(ol.index_select(0, rows), tuple(x.index_select(0, rows) for x in d),
                                              hf.index_select(0, rows)))
        t = torch.where(inside, t, torch.full_like(t, float("inf")))
        flat_t = t.reshape(-1)
        best = best.scatter_reduce(0, flat_pix, flat_t, reduce="amin", include_self=True)
        win = torch.isfinite(flat_t) & (flat_t == best.index_select(0, flat_pix))
        box_id = (gidx + 1)[:, None].expand_as(t).reshape(-1)
        # exact ties (touching faces): the highest id wins, whatever the thread count
        ids = ids.scatter_reduce(0, flat_pix[win], box_id[win], reduce="amax", include_self=False)
    return View(best.reshape(H, W), ids.reshape(H, W), T_w_c, K, frame, centre, yaw, cos_all, sin_all, o_all,
                rays_w)


def box_local_points(scene: Scene, view: View, rays: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
    """(S,3) hit points in their box's local frame for flat pixel indices ``sel`` (which must hit boxes)."""
    m = view.ids.reshape(-1).index_select(0, sel) - 1
    # hit points in world axes, relative to the camera
    p_rel = view.rays_w.index_select(0, sel) * view.depth.reshape(-1).index_select(0, sel)[:, None]
    return (yaw_rotate(p_rel, view.box_cos.index_select(0, m), view.box_sin.index_select(0, m), inverse=True)
            + view.box_o.index_select(0, m))


def sun_shadowed(scene: Scene, view: View, sel: torch.Tensor, towards_sun: torch.Tensor,
                 chunk: int = 4096) -> torch.Tensor:
    """(S,) bool: the hit points of the flat pixels ``sel`` (ground or object hits of ``view``) lie in an object's
    cast shadow, i.e. the ray from the point towards the sun (``towards_sun``: (3,) unit vector, world axes) meets a
    box or ellipsoid of the scene (posed at the view's frame) farther than ``NEAR`` from it. A point on a face
    turned from the sun is "shadowed" by its own object (its Lambert term is already the ambient one).

    The (point, object) pairs whose ray passes the object's bounding sphere are tested exactly (slab test or the
    ellipsoid's far root), ``chunk`` points at a time, in box-local coordinates from the camera-relative hit points
    (as :func:`box_local_points`), so the test keeps the casting's precision far from the origin."""
    dev = view.depth.device
    p_rel = view.rays_w.index_select(0, sel) * view.depth.reshape(-1).index_select(0, sel)[:, None]  # (S,3)
    M = len(scene.half)
    out = torch.zeros(len(sel), dtype=torch.bool, device=dev)
    if M == 0 or len(sel) == 0:
        return out
    sun_w = towards_sun.to(dev).float()
    sun = yaw_rotate(sun_w[None].expand(M, 3), view.box_cos, view.box_sin, inverse=True)  # (M,3) box axes
    hf = torch.from_numpy(scene.half).float().to(dev)  # (M,3)
    radius = hf.norm(dim=-1)
    is_ell = torch.from_numpy(scene.shape == SHAPE_ELLIPSOID).to(dev)
    centre = torch.from_numpy(view.box_centre - view.T_w_c[:3, 3]).float().to(dev)  # (M,3) camera-relative
    for start in range(0, len(sel), chunk):
        p = p_rel[start:start + chunk]
        w = centre[:, None, :] - p[None]  # (M,N,3) point to box centre
        along = w @ sun_w  # (M,N)
        near_ray = (along > -radius[:, None]) & ((w * w).sum(-1) - along * along < (radius * radius)[:, None])
        m, n = torch.nonzero(near_ray, as_tuple=True)
        if len(m) == 0:
            continue
        c, s = view.box_cos.index_select(0, m), view.box_sin.index_select(0, m)
        x, y, z = p.index_select(0, n).unbind(-1)
        o = view.box_o.index_select(0, m)
        q = torch.stack([c * x - s * z, y, s * x + c * z], -1) + o  # (K,3) box-local points
        d, h = sun.index_select(0, m), hf.index_select(0, m)
        # boxes: the slab test, a hit when the exit lies beyond NEAR and after the entry
        t1, t2 = (-h - q) / d, (h - q) / d
        t_near = torch.minimum(t1, t2).amax(-1)
        t_far = torch.maximum(t1, t2).amin(-1)
        hit = (t_far >= t_near) & (t_far > NEAR)
        ell = torch.nonzero(is_ell.index_select(0, m)).squeeze(1)
        if len(ell):  # ellipsoids: the far root of |(q + t d) / h|^2 = 1 beyond NEAR
            qe, e = q[ell] / h[ell], d[ell] / h[ell]
            a, b = (e * e).sum(-1), (qe * e).sum(-1)
            disc = b * b - a * ((qe * qe).sum(-1) - 1.0)
            hit[ell] = (disc >= 0) & ((-b + disc.clamp_min(0).sqrt()) / a > NEAR)
        out[start:start + chunk] |= torch.zeros(len(p), dtype=torch.bool, device=dev).index_put_((n,), hit,
                                                                                              accumulate=True)
    return out


def flow_between(scene: Scene, a: View, b: View, rays: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact flow from view ``a`` to view ``b`` (same intrinsics and size) and its validity.

    Every pixel of ``a`` is lifted with its depth, moved with its object's motion between the two frames
    (the camera motion alone for the ground and static boxes; rotation only for sky, a point at infinity)
    and projected into ``b``.

    Returns:
        flow (2,H,W) float32 in pixels, and valid (1,H,W) bool: not sky, in front of camera b, landing
        inside image b (``0 <= u <= W-1``, ``0 <= v <= H-1``), and not hidden by a nearer surface of ``b``:
        among the 2x2 pixels of ``b`` around the landing point, one showing the same surface (box id) must
        be at least as far, within 1 % + 1 cm (this also rejects faces that turned away, which are behind
        the same box's visible faces).
    """
    H, W = a.depth.shape
    K = a.K
    ids = a.ids.reshape(-1)
    sky = ids < 0
    depth = torch.where(sky, torch.ones_like(a.depth.reshape(-1)), a.depth.reshape(-1))
    p_a = rays * depth[:, None]
    T_b_a = np.linalg.inv(b.T_w_c) @ a.T_w_c
    dev = rays.device
    R = torch.from_numpy(T_b_a[:3, :3]).float().to(dev)
    t = torch.from_numpy(T_b_a[:3, 3]).float().to(dev)
    p_b = p_a @ R.T + torch.where(sky[:, None], torch.zeros(1, 3, device=dev), t[None])
    # moving boxes: their own motion between the frames
    V = scene.num_dynamic
    M = len(scene.half)
    dyn_ids = np.arange(M - V, M) + 1
    moved = V > 0 and not (np.array_equal(a.box_centre[-V:], b.box_centre[-V:])
                           and np.array_equal(a.box_yaw[-V:], b.box_yaw[-V:]))
    if moved:
        sel = torch.nonzero(ids >= int(dyn_ids[0])).squeeze(1)
        if len(sel):
            p_loc = box_local_points(scene, a, rays, sel)
            m = ids[sel] - 1
            # box-local -> camera b: p_b = R_c_w R_y(yaw_b) (p_loc - o_loc_b)
            p_rel = yaw_rotate(p_loc - b.box_o[m], b.box_cos[m], b.box_sin[m])
            p_b[sel] = p_rel @ torch.from_numpy(b.T_w_c[:3, :3]).float().to(dev)
    z = p_b[:, 2]
    zs = torch.where(z.abs() < 1e-8, torch.full_like(z, 1e-8), z)
    u = K[0, 0] * p_b[:, 0] / zs + K[0, 2]
    v = K[1, 1] * p_b[:, 1] / zs + K[1, 2]
    grid_u = torch.arange(W, dtype=torch.float32, device=dev).repeat(H)
    grid_v = torch.arange(H, dtype=torch.float32, device=dev).repeat_interleave(W)
    flow = torch.stack([u - grid_u, v - grid_v], 0).reshape(2, H, W)
    valid = (~sky) & (z > NEAR) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    # occlusion: compare with the nearest same-surface neighbour depth in b
    u0 = u.clamp(0, W - 1).floor().long()
    v0 = v.clamp(0, H - 1).floor().long()
    bd = b.depth.reshape(-1)
    bi = b.ids.reshape(-1)
    far = torch.full_like(z, -1.0)
    for du in (0, 1):
        for dv in (0, 1):
            q = (v0 + dv).clamp(max=H - 1) * W + (u0 + du).clamp(max=W - 1)
            same = bi.index_select(0, q) == ids
            far = torch.maximum(far, torch.where(same, bd.index_select(0, q), torch.full_like(z, -1.0)))
    valid &= z <= far * 1.01 + 0.01
    return flow, valid.reshape(1, H, W)
