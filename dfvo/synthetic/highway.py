"""The highway scenario: a gently curving motorway route, the camera's motion on it, and traffic at its own speeds.

Convention:
    World frame as in :mod:`dfvo.synthetic.trajectory` (x right, y down, z forward at the start, ground
    ``y = CAMERA_HEIGHT``, the camera centre at ``y = 0``). The route's centre line is the median of a dual
    carriageway: ``lateral > 0`` is the camera's carriageway (lanes 0..L-1 from the median outwards, driving
    towards increasing arc length s), ``lateral < 0`` the oncoming one. Curvature ``kappa > 0`` turns right.
    Speeds are metres per frame (KITTI records at 10 Hz: 2.5 m/frame = 25 m/s = 90 km/h).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from dfvo.synthetic.trajectory import Trajectory, draw_speed, heading_vec, right_vec, yaw_pose

HIGHWAY_SPEED = (2.0, 3.0)  # default cruise speed range of the camera, m/frame
LANE_WIDTH = 3.6
MEDIAN_HALF = 1.6  # median centre line to the inner edge of the first lane (barrier in the middle)
SHOULDER = 2.6  # hard shoulder beyond the outer lane
RAIL_GAP = 0.5  # guard rail beyond the shoulder
# vehicle boxes: (width, height, length), probability; trucks keep to the outer two lanes
VEHICLES = (((1.8, 1.45, 4.4), 0.6), ((1.95, 1.9, 5.0), 0.25), ((2.5, 3.6, 12.5), 0.15))


class HighwayRoute:
    """Median centre line made of constant-curvature pieces, with the carriageway layout.

    Args:
        pieces: (length in metres, curvature in 1/m) from s = 0; the first piece should be straight (negative s
            extrapolates it), the last is extended indefinitely.
        lanes: lanes per carriageway.
        camera_s: (N,) arc length of the camera per frame (the scene is laid out around it).
    """

    def __init__(self, pieces: list[tuple[float, float]], lanes: int, camera_s: np.ndarray) -> None:
        self.prims: list[tuple[float, float, np.ndarray, float, float]] = []  # (s0, length, p0, theta0, kappa)
        p, theta, s = np.zeros(2), 0.0, 0.0
        for i, (length, kappa) in enumerate(pieces):
            self.prims.append((s, length if i < len(pieces) - 1 else length + 1e6, p.copy(), theta, float(kappa)))
            p, theta = self._advance(p, theta, float(kappa), length)
            s += length
        self.lanes = int(lanes)
        self.camera_s = np.asarray(camera_s, dtype=np.float64)
        self.legs: list = []  # no street legs (the street worlds' lane markings)

    @staticmethod
    def _advance(p: np.ndarray, theta: float, kappa: float, ds: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        ds = np.asarray(ds, dtype=np.float64)
        th = theta + kappa * ds
        if kappa == 0.0:
            return p + ds[..., None] * heading_vec(np.full(ds.shape, theta)), th
        return p + (right_vec(np.array(theta)) - right_vec(th)) / kappa, th

    def lane_centre(self, lane: int) -> float:
        """Lateral offset of lane ``lane`` (0 next to the median) of the camera's carriageway."""
        return MEDIAN_HALF + LANE_WIDTH * (lane + 0.5)

    @property
    def road_edge(self) -> float:
        """Lateral offset of the outer edge of the outer lane."""
        return MEDIAN_HALF + LANE_WIDTH * self.lanes

    @property
    def rail(self) -> float:
        """Lateral offset of the guard rails (both carriageways, mirrored)."""
        return self.road_edge + SHOULDER + RAIL_GAP

    def pose(self, s: np.ndarray, lateral: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Position (...,2) (x, z) and heading (...) at arc lengths ``s`` (...) with a lateral offset."""
        s = np.asarray(s, dtype=np.float64)
        lat = np.broadcast_to(np.asarray(lateral, dtype=np.float64), s.shape)
        pos = np.zeros(s.shape + (2,))
        theta = np.zeros(s.shape)
        for i, (s0, length, p0, th0, kappa) in enumerate(self.prims):
            sel = (s >= s0) & (s < s0 + length) if i > 0 else s < s0 + length
            if sel.any():
                pos[sel], theta[sel] = self._advance(p0, th0, kappa, s[sel] - s0)
        return pos + lat[..., None] * right_vec(theta), theta

    def to_route(self, x: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Route coordinates (arc length, lateral offset), each (S,), of world points x (S,), z (S,) (any device):
        the piece whose normal through the point is nearest to it."""
        best_lat = torch.full_like(x, float("inf"))
        best_s = torch.zeros_like(x)
        for i, (s0, length, p0, th0, kappa) in enumerate(self.prims):
            dx, dz = x - float(p0[0]), z - float(p0[1])
            if kappa == 0.0:
                along = dx * math.sin(th0) + dz * math.cos(th0)
                lat = dx * math.cos(th0) - dz * math.sin(th0)
            else:
                cx, cz = math.cos(th0) / kappa, -math.sin(th0) / kappa  # centre relative to p0
                wx, wz = dx - cx, dz - cz
                r = torch.sqrt(wx * wx + wz * wz)
                sg = math.copysign(1.0, kappa)
                th = torch.atan2(sg * wz, -sg * wx)  # heading whose right vector points away from the centre
                along = torch.remainder(th - th0 + math.pi, 2 * math.pi) - math.pi
                along = along / kappa
                lat = 1.0 / kappa - sg * r
            ok = (along <= length) & ((along >= 0) if i > 0 else torch.ones_like(along, dtype=torch.bool))
            better = ok & (lat.abs() < best_lat.abs())
            best_lat = torch.where(better, lat, best_lat)
            best_s = torch.where(better, along + s0, best_s)
        return best_s, best_lat


def make_highway_trajectory(num_frames: int, seed: int,
                            speed: float | tuple[float, float] | None = None) -> Trajectory:
    """Camera poses on a dual-carriageway motorway and the traffic around it (deterministic in ``seed``).

    Args:
        num_frames: N >= 2.
        seed: world seed.
        speed: the camera's cruise speed in m/frame, or a (lo, hi) range drawn per world (default
            ``HIGHWAY_SPEED``); it varies by +-3 % along the sequence.

    Returns:
        A :class:`~dfvo.synthetic.trajectory.Trajectory` whose ``route`` is a :class:`HighwayRoute` and
        whose segments are all "highway".
    """
    if num_frames < 2:
        raise ValueError(f"SyntheticWorld: num_frames={num_frames}; expected at least 2")
    rng = np.random.default_rng([seed, 0x4817])
    cruise = draw_speed(speed, HIGHWAY_SPEED, rng)
    lanes = int(rng.integers(2, 5))
    cam_lane = int(rng.integers(0, lanes))
    n = num_frames
    k = np.arange(n, dtype=np.float64)
    step = cruise * (1.0 + 0.025 * np.sin(0.05 * k + seed) + 0.008 * np.sin(0.31 * k + 2 * seed))
    s = np.cumsum(step) - step[0]
    pieces: list[tuple[float, float]] = [(float(rng.uniform(40.0, 250.0)), 0.0)]
    total = float(s[-1]) + 900.0
    while sum(p[0] for p in pieces) < total:
        radius = float(rng.uniform(350.0, 1500.0))
        angle = math.radians(float(rng.uniform(3.0, 18.0)))
        pieces.append((radius * angle, float(rng.choice([-1.0, 1.0])) / radius))
        pieces.append((float(rng.uniform(60.0, 400.0)), 0.0))
    route = HighwayRoute(pieces, lanes, s)
    # small wander inside the lane; the heading follows the path (lateral slope)
    amp, period, phase = 0.12, float(rng.uniform(50.0, 90.0)), float(rng.uniform(0, 2 * math.pi))
    lateral = route.lane_centre(cam_lane) + amp * np.sin(2 * math.pi * k / period + phase)
    slope = amp * 2 * math.pi / period * np.cos(2 * math.pi * k / period + phase) / np.maximum(step, 1e-3)
    pos, theta = route.pose(s, lateral)
    poses = np.zeros((n, 4, 4))
    for i in range(n):
        pitch = math.radians(0.3) * math.sin(0.41 * i + seed) + math.radians(0.1) * math.sin(1.3 * i)
        roll = math.radians(0.2) * math.sin(0.23 * i + 2 * seed)
        poses[i] = yaw_pose(pos[i, 0], pos[i, 1], theta[i] + math.atan(slope[i]), pitch, roll)
    tracks, sizes = _traffic(route, cruise, cam_lane, n, rng)
    return Trajectory(route, poses, ["highway"] * n, tracks, sizes, [])


def _traffic(route: HighwayRoute, cruise: float, cam_lane: int, n: int,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Vehicles per lane, each lane at its own speed (so a lane's vehicles never meet): faster towards the median,
    slower outside, the camera's lane only ahead and faster than the camera; oncoming lanes at -0.8..-1.15 of
    the camera's speed. Placed so traffic is around the camera for the whole sequence.

    Returns:
        tracks (N,V,4) (x, z, yaw, present) and sizes (V,3) (width, height, length).
    """
    k = np.arange(n, dtype=np.float64)
    s_all, lat_all, yaw_flip, sizes = [], [], [], []
    sizes_p = np.array([p for _, p in VEHICLES])
    L = route.lanes
    for lane in range(-L, L):  # negative: oncoming lane -1-lane
        oncoming = lane < 0
        idx = -1 - lane if oncoming else lane
        if oncoming:
            v = -cruise * float(rng.uniform(0.8, 1.15))
        elif lane == cam_lane:
            v = cruise * (1.0 + float(rng.uniform(0.03, 0.2)))
        else:
            v = cruise * (1.0 + float(rng.uniform(-0.2, 0.2)) + 0.1 * (cam_lane - lane))
        rel = v - cruise  # speed relative to the camera
        lo = 18.0 + float(rng.uniform(0, 25)) if lane == cam_lane else min(-40.0, -40.0 - rel * n)
        hi = max(260.0, 260.0 - rel * n)
        r = lo + float(rng.uniform(0, 15))
        while r < hi:
            pick = int(rng.choice(len(VEHICLES), p=sizes_p))
            if pick == 2 and idx < L - 2:
                pick = 0
            size = VEHICLES[pick][0]
            s_all.append(r + v * k)
            sway = 0.15 * np.sin(2 * math.pi * k / float(rng.uniform(60, 120)) + float(rng.uniform(0, 6.3)))
            lat_all.append((-1.0 if oncoming else 1.0) * route.lane_centre(idx) + sway)
            yaw_flip.append(math.pi if oncoming else 0.0)
            sizes.append(size)
            r += size[2] + float(rng.uniform(20.0, 110.0 if oncoming else 80.0))
    S = np.stack(s_all, 1)
    pos, theta = route.pose(S, np.stack(lat_all, 1))
    yaw = theta + np.array(yaw_flip)[None, :]
    tracks = np.concatenate([pos, yaw[..., None], np.ones_like(yaw)[..., None]], -1)
    return tracks, np.array(sizes, dtype=np.float64)
