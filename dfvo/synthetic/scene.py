"""Scene container of the synthetic worlds, and the street layout: ground plane plus boxes (pavements, buildings,
poles, parked and moving cars). The highway layout is :mod:`dfvo.synthetic.highway_scene`.

Convention:
    World frame as in :mod:`dfvo.synthetic.trajectory` (x right, y down, z forward; ground plane
    ``y = CAMERA_HEIGHT``). Every object is oriented by a yaw about +y: ``T_w_o = [R_y(yaw) | centre]``;
    its local axes are (x: across the street, y: down, z: along the street) with half sizes ``half``; it is
    that box, or the ellipsoid inscribed in it (``shape``). Ids used by the renderer: -1 sky, 0 ground,
    ``1 + m`` object ``m``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from dfvo.synthetic.textures import asphalt, band
from dfvo.synthetic.trajectory import CAMERA_HEIGHT, PARKING, Leg, Route, Trajectory

ROAD_HALF_WIDTH = 6.5  # kerb line
FACADE = 9.0  # building front line (pavement 2.5 m wide)
CORNER_DEPTH = 29.0  # how far the inner corner block reaches
CURB_HEIGHT = 0.15

KIND_PAVEMENT, KIND_BUILDING, KIND_POLE, KIND_CAR = 1, 2, 3, 4
KIND_BARRIER, KIND_RAIL, KIND_TERRAIN, KIND_FOLIAGE, KIND_SIGN, KIND_WALL = 5, 6, 7, 8, 9, 10
KIND_PRINT = 11  # printed matter seen from close by (the hand-held world's walls, papers and books)
SHAPE_BOX, SHAPE_ELLIPSOID = 0, 1
DRAW_DISTANCE = 250.0  # objects whose nearest possible point is farther are not drawn (unless ``cull`` says so)

GroundShader = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class Scene:
    """Boxes of one world. Static boxes first, then the ``V`` moving vehicles (last ``V`` boxes).

    Attributes:
        centre: (M,3) float64 world centres of the static layout (vehicle rows are overwritten per frame).
        yaw: (M,) yaw of each box.
        half: (M,3) half sizes in the box's local axes.
        kind: (M,) int material kind (KIND_*).
        color: (M,3) base colour in [0,1].
        seed: (M,) int texture seed.
        num_dynamic: number of moving vehicles (the last boxes).
        tracks: (N,V,4) vehicle (x, z, yaw, present) per frame.
        shape: (M,) ``SHAPE_BOX`` or ``SHAPE_ELLIPSOID`` (default: all boxes).
        cull: (M,) drawing distance of each object in metres (default ``DRAW_DISTANCE``; inf = always drawn).
        ground: colour (S,3) of the ground at world points x (S,), z (S,) with footprint fp (S,) (metres per
            pixel), before lighting (default: plain asphalt).
    """

    centre: np.ndarray
    yaw: np.ndarray
    half: np.ndarray
    kind: np.ndarray
    color: np.ndarray
    seed: np.ndarray
    num_dynamic: int
    tracks: np.ndarray
    shape: np.ndarray | None = None
    cull: np.ndarray | None = None
    ground: GroundShader | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        M = len(self.half)
        if self.shape is None:
            self.shape = np.full(M, SHAPE_BOX, dtype=np.int64)
        if self.cull is None:
            self.cull = np.full(M, DRAW_DISTANCE)
        if self.ground is None:
            self.ground = street_ground([])

    def box_poses(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(M,3) centres and (M,) yaws of all boxes at ``frame``."""
        centre = self.centre.copy()
        yaw = self.yaw.copy()
        V = self.num_dynamic
        if V:
            tr = self.tracks[frame]
            centre[-V:, 0] = tr[:, 0]
            centre[-V:, 2] = tr[:, 1]
            yaw[-V:] = tr[:, 2]
        return centre, yaw


def rot_y(yaw: np.ndarray) -> np.ndarray:
    """(...,3,3) rotations about +y."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def street_ground(legs: list[Leg]) -> GroundShader:
    """Ground colour of the street worlds: asphalt with a dashed centre line and edge lines along each leg."""

    def shade(x: torch.Tensor, z: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
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
        return g[:, None] * torch.tensor([0.97, 0.98, 1.03], device=x.device)

    return shade


def _in_clear(s: float, side: int, clear: list[tuple[float, float, int]]) -> bool:
    return any(lo <= s <= hi and (cs == 0 or cs == side) for lo, hi, cs in clear)


def build_scene(traj: Trajectory, seed: int) -> Scene:
    """Lay out pavements, building rows, poles and parked cars along the route's legs (deterministic)."""
    rng = np.random.default_rng(seed + 7919)
    route: Route = traj.route
    rows: list[tuple] = []  # (centre xyz, yaw, half xyz, kind, colour, seed)
    legs = route.legs
    arc = 0.5 * math.pi * route.radius
    s_start = 0.0
    for li, leg in enumerate(legs):
        head = np.array([math.sin(leg.theta), math.cos(leg.theta)])
        right = np.array([math.cos(leg.theta), -math.sin(leg.theta)])
        # route arc length of along-position 0 of this leg (the previous corner point)
        if li > 0:
            s_start = route.prims[2 * li - 1][1] + arc - route.radius

        def world(along: float, lat: float, _h=head, _r=right, _p=leg.start) -> tuple[float, float]:
            p = _p + along * _h + lat * _r
            return float(p[0]), float(p[1])

        for side in (1, -1):
            first, last = li == 0, li == len(legs) - 1
            if first:
                b0 = p0 = -40.0
            elif side == leg.turn_in:
                b0, p0 = FACADE, ROAD_HALF_WIDTH
            else:
                b0 = p0 = -CORNER_DEPTH
            if last:
                b1 = p1 = leg.length
            elif side == leg.turn_out:
                b1 = p1 = leg.length - CORNER_DEPTH
            else:
                b1, p1 = leg.length + FACADE, leg.length + ROAD_HALF_WIDTH
            # pavement slab under the row
            lat_c = side * 0.5 * (ROAD_HALF_WIDTH + FACADE + 25.0)
            x, z = world(0.5 * (p0 + p1), lat_c)
            rows.append(([x, CAMERA_HEIGHT - CURB_HEIGHT / 2, z], leg.theta,
                         [0.5 * (FACADE + 25.0 - ROAD_HALF_WIDTH), CURB_HEIGHT / 2, 0.5 * (p1 - p0)],
                         KIND_PAVEMENT, [0.62, 0.60, 0.57], int(rng.integers(1 << 20))))
            # buildings
            a = b0
            while a < b1 - 1.0:
                length = min(float(rng.uniform(8.0, 22.0)), b1 - a)
                depth = float(rng.uniform(10.0, 20.0))
                height = float(rng.uniform(6.0, 24.0))
                x, z = world(a + 0.5 * length, side * (FACADE + 0.5 * depth))
                hue = rng.uniform(0.35, 0.85, size=3) * np.array([1.0, 0.85, 0.75])
                rows.append(([x, CAMERA_HEIGHT - CURB_HEIGHT - height / 2, z], leg.theta,
                             [depth / 2, height / 2, length / 2], KIND_BUILDING, hue.tolist(),
                             int(rng.integers(1 << 20))))
                a += length
                if rng.random() < 0.15 and not _in_clear(s_start + a, side, traj.clear):
                    a += 3.0  # alley
            # poles on the pavement
            a = p0 + float(rng.uniform(2.0, 12.0))
            while a < p1 - 2.0:
                if not _in_clear(s_start + a, side, traj.clear):
                    x, z = world(a, side * (ROAD_HALF_WIDTH + 0.5))
                    rows.append(([x, CAMERA_HEIGHT - CURB_HEIGHT - 2.5, z], leg.theta, [0.09, 2.5, 0.09], KIND_POLE,
                                 [0.45, 0.46, 0.48], int(rng.integers(1 << 20))))
                a += float(rng.uniform(12.0, 25.0))
            # parked cars on the road edge, away from intersections
            a = max(p0, 0.0 if first else 2 * FACADE) + float(rng.uniform(2.0, 8.0))
            end = p1 - (0.0 if last else 2 * FACADE)
            while a < end:
                if rng.random() < 0.6 and not _in_clear(s_start + a, side, traj.clear):
                    x, z = world(a, side * PARKING)
                    yaw = leg.theta + float(rng.uniform(-0.05, 0.05))
                    rows.append(([x, CAMERA_HEIGHT - 0.75, z], yaw, [0.9, 0.75, 2.1], KIND_CAR,
                                 rng.uniform(0.1, 0.9, size=3).tolist(), int(rng.integers(1 << 20))))
                a += float(rng.uniform(5.5, 12.0))
    V = traj.tracks.shape[1]
    for v in range(V):
        w, h, length = traj.track_sizes[v]
        rows.append(([0.0, CAMERA_HEIGHT - h / 2, 0.0], 0.0, [w / 2, h / 2, length / 2], KIND_CAR,
                     rng.uniform(0.1, 0.9, size=3).tolist(), int(rng.integers(1 << 20))))
    return Scene(
        centre=np.array([r[0] for r in rows], dtype=np.float64),
        yaw=np.array([r[1] for r in rows], dtype=np.float64),
        half=np.array([r[2] for r in rows], dtype=np.float64),
        kind=np.array([r[3] for r in rows], dtype=np.int64),
        color=np.array([r[4] for r in rows], dtype=np.float64),
        seed=np.array([r[5] for r in rows], dtype=np.int64),
        num_dynamic=V,
        tracks=traj.tracks,
        ground=street_ground(legs),
    )
