"""Layout of the highway scenario: median barrier, guard rails, sparse roadside objects (trees, signs, noise walls,
lamp posts), forest edges and distant hills, plus the road surface (lanes, markings, verges).

Convention:
    Objects and ids as in :mod:`dfvo.synthetic.scene`; route coordinates as in
    :mod:`dfvo.synthetic.highway`. Hills and forest edges are ellipsoids half sunk into the ground; hills
    are always drawn (no drawing distance), so the far terrain (~100-500 m) never pops in or out.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from dfvo.synthetic.highway import MEDIAN_HALF, SHOULDER, HighwayRoute
from dfvo.synthetic.scene import (
    DRAW_DISTANCE,
    KIND_BARRIER,
    KIND_CAR,
    KIND_FOLIAGE,
    KIND_POLE,
    KIND_RAIL,
    KIND_SIGN,
    KIND_TERRAIN,
    KIND_WALL,
    SHAPE_BOX,
    SHAPE_ELLIPSOID,
    GroundShader,
    Scene,
)
from dfvo.synthetic.textures import asphalt, band, grass, lines
from dfvo.synthetic.trajectory import CAMERA_HEIGHT, Trajectory

SEGMENT = 12.0  # length of the straight pieces that approximate barriers, rails and walls along curves


def highway_ground(route: HighwayRoute) -> GroundShader:
    """Ground colour: asphalt carriageways with solid edge lines and dashed lane lines (4 m every 12 m), the
    median strip, hard shoulders, then grass verges and fields."""
    edge = route.road_edge
    verge = edge + SHOULDER + 0.3

    def shade(x: torch.Tensor, z: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
        along, lat = route.to_route(x, z)
        a = lat.abs()
        mark = torch.maximum(band(a, MEDIAN_HALF + 0.1, MEDIAN_HALF + 0.3, fp), band(a, edge - 0.3, edge - 0.1, fp))
        dash = lines(along - 2.0, 12.0, 4.0, fp)
        for lane in range(1, route.lanes):
            c = MEDIAN_HALF + lane * 3.6
            mark = torch.maximum(mark, band(a, c - 0.075, c + 0.075, fp) * dash)
        g = asphalt(x, z, fp) * 0.92
        road = (g * (1 - mark) + 0.85 * mark)[:, None] * torch.tensor([0.97, 0.98, 1.03], device=x.device)
        green = ((a - verge) / fp.clamp_min(1e-4) + 0.5).clamp(0, 1)[:, None]
        return road * (1 - green) + grass(x, z, fp) * green

    return shade


class _Rows:
    """Accumulates objects: centre (x, y, z), yaw, half sizes, kind, colour, texture seed, shape, cull."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.rows: list[tuple] = []

    def add(self, centre: list[float], yaw: float, half: list[float], kind: int, color: list[float],
            shape: int = SHAPE_BOX, cull: float = DRAW_DISTANCE) -> None:
        self.rows.append((centre, yaw, half, kind, color, int(self.rng.integers(1 << 20)), shape, cull))

    def column(self, k: int) -> np.ndarray:
        return np.array([r[k] for r in self.rows])


def _chain(rows: _Rows, route: HighwayRoute, s0: float, s1: float, lat: float, half_w: float, height: float,
           kind: int, color: list[float]) -> None:
    """Straight pieces of ``SEGMENT`` metres between route points at lateral ``lat`` (chords of the offset curve)."""
    for a in np.arange(s0, s1, SEGMENT):
        (pa, pb), _ = route.pose(np.array([a, a + SEGMENT]), lat)
        mid, d = 0.5 * (pa + pb), pb - pa
        rows.add([mid[0], CAMERA_HEIGHT - height / 2, mid[1]], math.atan2(d[0], d[1]),
                 [half_w, height / 2, 0.5 * float(np.hypot(*d)) + 0.01], kind, color)


def _clear_of_road(route: HighwayRoute, x: float, z: float, yaw: float, hx: float, hz: float, margin: float) -> bool:
    """True when the ground footprint ellipse of an object stays ``margin`` metres beside the median line."""
    a = np.linspace(0, 2 * math.pi, 24, endpoint=False)
    lx, lz = hx * np.cos(a), hz * np.sin(a)
    px = x + math.cos(yaw) * lx + math.sin(yaw) * lz
    pz = z - math.sin(yaw) * lx + math.cos(yaw) * lz
    _, lat = route.to_route(torch.from_numpy(px), torch.from_numpy(pz))
    return bool((lat.abs() >= margin).all())


def build_highway_scene(traj: Trajectory, seed: int) -> Scene:
    """Static layout around the camera's stretch of the route, then the traffic (last boxes), deterministic."""
    route: HighwayRoute = traj.route
    rng = np.random.default_rng([seed, 0x5CE7])
    rows = _Rows(rng)
    s0, s1 = float(route.camera_s[0]) - 60.0, float(route.camera_s[-1]) + DRAW_DISTANCE + 60.0
    rail = route.rail
    _chain(rows, route, s0, s1, 0.0, 0.3, 0.85, KIND_BARRIER, [0.92, 0.9, 0.86])
    for side in (1.0, -1.0):
        _chain(rows, route, s0, s1, side * rail, 0.06, 0.75, KIND_RAIL, [0.8, 0.8, 0.8])
    if rng.random() < 0.5:  # lamp posts on the median
        for a in np.arange(s0 + rng.uniform(0, 40), s1, 45.0):
            (p,), (th,) = route.pose(np.array([a]), 0.0)
            rows.add([p[0], CAMERA_HEIGHT - 5.0, p[1]], th, [0.1, 5.0, 0.1], KIND_POLE, [0.55, 0.56, 0.58])
    for side in (1.0, -1.0):
        # noise walls on some stretches, trees in clusters elsewhere
        a = s0
        while a < s1:
            stretch = float(rng.uniform(80.0, 300.0))
            if rng.random() < 0.2:
                height = float(rng.uniform(2.5, 4.5))
                tone = float(rng.uniform(0.6, 0.9))
                _chain(rows, route, a, min(a + stretch, s1), side * (rail + 2.0), 0.15, height, KIND_WALL,
                       [tone, tone * 0.97, tone * 0.9])
            b = a
            while b < a + stretch:
                lat = side * (rail + float(rng.uniform(4.5, 30.0)))
                for _ in range(int(rng.integers(1, 6))):
                    _tree(rows, route, b + float(rng.uniform(-8, 8)), lat + side * float(rng.uniform(0, 6)))
                b += float(rng.uniform(25.0, 110.0))
            a += stretch
        # forest edges: long low ellipsoids 30-90 m out
        a = s0 - 100.0
        while a < s1 + 200.0:
            hx, hy, hz = float(rng.uniform(6, 15)), float(rng.uniform(6, 12)), float(rng.uniform(15, 60))
            (p,), (th,) = route.pose(np.array([a]), side * (rail + float(rng.uniform(25.0, 80.0)) + hx))
            rows.add([p[0], CAMERA_HEIGHT, p[1]], th, [hx, hy, hz], KIND_FOLIAGE,
                     [0.2, 0.3, 0.15], SHAPE_ELLIPSOID, 400.0)
            a += hz * float(rng.uniform(1.2, 3.5))
        # hills: large ellipsoids 90-300 m out, half sunk, always drawn
        a = s0 - 300.0
        while a < s1 + 600.0:
            hx, hy, hz = float(rng.uniform(40, 140)), float(rng.uniform(12, 55)), float(rng.uniform(60, 220))
            (p,), (th,) = route.pose(np.array([a]), side * (float(rng.uniform(90.0, 300.0)) + hx))
            if _clear_of_road(route, p[0], p[1], th, hx, hz, 60.0):
                rows.add([p[0], CAMERA_HEIGHT + float(rng.uniform(0.0, 0.35)) * hy, p[1]], th, [hx, hy, hz],
                         KIND_TERRAIN, [0.4, 0.5, 0.3], SHAPE_ELLIPSOID, math.inf)
            a += hz * float(rng.uniform(0.8, 1.6))
    # signs on the camera's side
    a = s0 + float(rng.uniform(20.0, 200.0))
    while a < s1:
        (p,), (th,) = route.pose(np.array([a]), rail + 1.5)
        rows.add([p[0], CAMERA_HEIGHT - 2.5, p[1]], th, [0.08, 2.5, 0.08], KIND_POLE, [0.5, 0.5, 0.52])
        w, h = float(rng.uniform(2.5, 4.5)), float(rng.uniform(1.5, 2.5))
        color = [0.08, 0.22, 0.6] if rng.random() < 0.5 else [0.05, 0.38, 0.2]
        rows.add([p[0], CAMERA_HEIGHT - 3.5 - h / 2, p[1]], th, [w / 2, h / 2, 0.05], KIND_SIGN, color)
        a += float(rng.uniform(250.0, 600.0))
    V = traj.tracks.shape[1]
    for v in range(V):  # traffic last: the moving boxes
        w, h, length = traj.track_sizes[v]
        rows.add([0.0, CAMERA_HEIGHT - h / 2, 0.0], 0.0, [w / 2, h / 2, length / 2], KIND_CAR,
                 rng.uniform(0.1, 0.9, size=3).tolist())
    return Scene(
        centre=rows.column(0).astype(np.float64), yaw=rows.column(1).astype(np.float64),
        half=rows.column(2).astype(np.float64), kind=rows.column(3).astype(np.int64),
        color=rows.column(4).astype(np.float64), seed=rows.column(5).astype(np.int64), num_dynamic=V,
        tracks=traj.tracks, shape=rows.column(6).astype(np.int64), cull=rows.column(7).astype(np.float64),
        ground=highway_ground(route),
    )


def _tree(rows: _Rows, route: HighwayRoute, s: float, lat: float) -> None:
    """A trunk (box) and a crown (ellipsoid) standing at route coordinates (s, lat)."""
    (p,), _ = route.pose(np.array([s]), lat)
    r = float(rows.rng.uniform(1.5, 3.5))
    ry = r * float(rows.rng.uniform(1.0, 1.6))
    trunk = float(rows.rng.uniform(1.2, 3.0))
    rows.add([p[0], CAMERA_HEIGHT - trunk / 2 - 0.2, p[1]], 0.0, [0.15, trunk / 2 + 0.2, 0.15], KIND_POLE,
             [0.35, 0.27, 0.2])
    rows.add([p[0], CAMERA_HEIGHT - trunk - ry * 0.9, p[1]], float(rows.rng.uniform(0, math.pi)), [r, ry, r],
             KIND_FOLIAGE, [0.2, 0.3, 0.15], SHAPE_ELLIPSOID)
