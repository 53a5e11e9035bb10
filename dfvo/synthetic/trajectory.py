"""Camera and vehicle trajectories of the synthetic driving world.

Convention:
    World frame: x right, y down (gravity along +y), z forward at the start; the ground is the plane
    ``y = CAMERA_HEIGHT`` and the camera centre stays at ``y = 0``. Headings ``theta`` are yaw angles
    about +y: ``theta = 0`` drives along +z, ``theta = +pi/2`` along +x (a right turn increases theta).
    Positions along the route are arc lengths ``s`` (metres) of the street centre line; ``lateral`` is
    the signed offset to the right of it. All arithmetic here is numpy float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CAMERA_HEIGHT = 1.65  # KITTI camera height above the road, metres
CORNER_RADIUS = 10.0  # radius of the street centre line in a 90-degree turn (default worlds)
LANE = 1.8  # lateral offset of the camera's lane centre (oncoming lane at -LANE)
PARKING = 4.6  # lateral offset of parked cars
PLANAR_LATERAL = 5.0  # lateral offset of the camera while it faces the right facade
HANDHELD_SCENARIOS = ("handheld", "handheld_planar")  # built by :mod:`dfvo.synthetic.handheld`
SCENARIOS = ("drive", "still", "rotation", "planar", "moving_car", "straight", "city", "highway", *HANDHELD_SCENARIOS)
# built here but "highway" (:mod:`dfvo.synthetic.highway`) and the hand-held ones
STREET_SCENARIOS = tuple(s for s in SCENARIOS if s not in ("highway", *HANDHELD_SCENARIOS))
CITY_SPEED = (0.4, 1.5)  # default cruise speed range of the "city" scenario, m/frame
TURN_RATE_DEG = (5.0, 10.0)  # yaw rate drawn per world for street corners once a speed is set (deg/frame)
TURN_RADIUS = (5.0, 12.0)  # limits of the corner radius (street centre line) once a speed is set (m)
BRAKE = 0.08  # braking / acceleration before and after corners, m/frame^2 (8 m/s^2 at 10 Hz)
LATERAL = 0.1  # most lateral acceleration in a corner, m/frame^2 (~1 g at 10 Hz): speed <= sqrt(LATERAL * radius)

# the default mixed sequence, repeated/truncated to num_frames: (segment, frames)
DRIVE_PATTERN = [("drive", 24), ("lane_out", 8), ("still", 5), ("rot_in", 12), ("planar", 8), ("rot_out", 12),
                 ("lane_in", 8), ("drive", 4), ("moving_car", 12), ("drive", 7)]


def heading_vec(theta: np.ndarray) -> np.ndarray:
    """(...,2) unit (x, z) direction of heading ``theta``."""
    return np.stack([np.sin(theta), np.cos(theta)], -1)


def right_vec(theta: np.ndarray) -> np.ndarray:
    """(...,2) unit (x, z) vector pointing to the right of heading ``theta``."""
    return np.stack([np.cos(theta), -np.sin(theta)], -1)


@dataclass
class Leg:
    """A straight street of the route: from ``start`` (x, z) along ``theta`` for ``length`` metres to the
    next intersection centre; ``turn_in``/``turn_out`` are the turn signs (+1 right, -1 left, 0 none) at its
    start and end."""

    start: np.ndarray
    theta: float
    length: float
    turn_in: int
    turn_out: int


class Route:
    """Street centre line: straights joined by 90-degree arcs of radius ``radius``.

    Args:
        corners: arc-length positions (metres) of the start of each arc, increasing, at least
            ``pi/2 * radius`` apart; turn signs alternate right, left, right, ...
        total: arc length the route must cover (the last straight is extended beyond it).
        radius: corner radius of the centre line, metres.
    """

    def __init__(self, corners: list[float], total: float, radius: float = CORNER_RADIUS) -> None:
        self.radius = float(radius)
        arc = 0.5 * math.pi * self.radius
        self.prims: list[tuple] = []  # (kind, s0, length, p0 (x,z), theta0, sign)
        p = np.zeros(2)
        theta, s, sign = 0.0, 0.0, 1
        for c in corners:
            if c < s:
                raise ValueError(f"synthetic route: corner at s={c} overlaps the previous turn (ends at {s})")
            self.prims.append(("line", s, c - s, p.copy(), theta, 0))
            p = p + (c - s) * heading_vec(np.array(theta))
            self.prims.append(("arc", c, arc, p.copy(), theta, sign))
            turned = np.array(theta + sign * math.pi / 2)
            p = p + sign * self.radius * (right_vec(np.array(theta)) - right_vec(turned))
            theta += sign * math.pi / 2
            s = c + arc
            sign = -sign
        self.prims.append(("line", s, max(total - s, 0.0) + 1e6, p.copy(), theta, 0))
        self.legs = self._legs()

    def pose(self, s: np.ndarray, lateral: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Position (...,2) (x, z) and heading (...) at arc lengths ``s`` with a lateral offset.

        Negative ``s`` extrapolates the first straight backwards.
        """
        s = np.asarray(s, dtype=np.float64)
        lat = np.broadcast_to(np.asarray(lateral, dtype=np.float64), s.shape)
        pos = np.zeros(s.shape + (2,))
        theta = np.zeros(s.shape)
        for i, (kind, s0, length, p0, th0, sign) in enumerate(self.prims):
            sel = (s >= s0) & (s < s0 + length) if i > 0 else s < s0 + length
            if not sel.any():
                continue
            ds = s[sel] - s0
            if kind == "line":
                pos[sel] = p0 + ds[:, None] * heading_vec(np.full(ds.shape, th0))
                theta[sel] = th0
            else:
                th = th0 + sign * ds / self.radius
                pos[sel] = p0 + sign * self.radius * (right_vec(np.array(th0)) - right_vec(th))
                theta[sel] = th
        pos = pos + lat[..., None] * right_vec(theta)
        return pos, theta

    def _legs(self) -> list[Leg]:
        """Straight streets between intersection centres (the arcs' corner points)."""
        legs: list[Leg] = []
        start, theta, turn_in = self.prims[0][3], self.prims[0][4], 0
        for kind, _s0, _length, p0, th0, sign in self.prims:
            if kind != "arc":
                continue
            vertex = p0 + self.radius * heading_vec(np.array(th0))
            legs.append(Leg(start.copy(), theta, float(np.linalg.norm(vertex - start)), turn_in, sign))
            start, theta, turn_in = vertex, th0 + sign * math.pi / 2, sign
        last = self.prims[-1]
        end = last[3] + (last[2] - 1e6 + 150.0) * heading_vec(np.array(last[4]))
        legs.append(Leg(start.copy(), theta, float(np.linalg.norm(end - start)), turn_in, 0))
        return legs


def yaw_pose(x: float, z: float, theta: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """(4,4) ``T_w_c`` of a camera at (x, 0, z) with yaw ``theta`` (about +y), then pitch, then roll."""
    cy, sy = math.cos(theta), math.sin(theta)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    cp, sp = math.cos(pitch), math.sin(pitch)
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    cr, sr = math.cos(roll), math.sin(roll)
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Ry @ Rx @ Rz
    T[0, 3], T[2, 3] = x, z
    return T


@dataclass
class Trajectory:
    """Per-frame camera motion and the moving vehicles of one sequence.

    Attributes:
        route: the street centre line.
        poses: (N,4,4) camera ``T_w_c``.
        segments: per-frame segment name (drive, turn, still, rotation, planar, moving_car).
        tracks: (N,V,4) moving vehicles per frame as (x, z, yaw, present) in the world frame.
        track_sizes: (V,3) full box sizes (width, height, length) of the vehicles.
        clear: list of (s_min, s_max, lateral side +1/-1/0 for both) where no street furniture may stand.
    """

    route: Route
    poses: np.ndarray
    segments: list[str]
    tracks: np.ndarray
    track_sizes: np.ndarray
    clear: list[tuple[float, float, int]]


def _schedule(scenario: str, n: int, rng: np.random.Generator) -> list[str]:
    if scenario == "drive":
        labels = [name for name, k in DRIVE_PATTERN for _ in range(k)]
        return [labels[i % len(labels)] for i in range(n)]
    if scenario in ("straight", "city"):
        return ["drive"] * n
    return [scenario] * n


def draw_speed(value: float | tuple[float, float] | None, default: tuple[float, float],
               rng: np.random.Generator) -> float:
    """A world's value of a setting: ``value`` itself (a number), a uniform draw in ``value = (lo, hi)``, or a
    uniform draw in ``default`` when ``value`` is None."""
    if value is not None and not isinstance(value, (tuple, list)):
        return float(value)
    lo, hi = default if value is None else value
    return float(lo + (float(hi) - float(lo)) * rng.random())


def make_trajectory(scenario: str, num_frames: int, seed: int, speed: float | tuple[float, float] | None = None,
                    turn_rate: float | tuple[float, float] | None = None) -> Trajectory:
    """Build the camera poses and vehicle tracks of a street scenario (deterministic in ``seed``).

    Args:
        scenario: one of ``STREET_SCENARIOS``.
        num_frames: N >= 2.
        seed: world seed.
        speed: cruise speed in m/frame, or a (lo, hi) range drawn per world; None keeps the default worlds
            (0.9-1.2 m/frame, 10 m corners taken at cruise speed; "city": a speed drawn in ``CITY_SPEED``).
        turn_rate: yaw rate in street corners, deg/frame, or a (lo, hi) range drawn per world (default
            ``TURN_RATE_DEG`` once ``speed`` or ``turn_rate`` is set, and in "city"). The corner radius
            follows (about ``speed / turn_rate``, within ``TURN_RADIUS``: tight corners at low speed), and the
            camera brakes (``BRAKE``) before a corner to ``turn_rate * radius``, at most ``sqrt(LATERAL *
            radius)`` (yaw rate = speed / radius: 5-10 deg/frame at 0.4-1 m/frame, ~5 at higher speeds).
    """
    if scenario not in STREET_SCENARIOS:
        raise ValueError(f"SyntheticWorld: scenario={scenario!r}; expected one of {SCENARIOS}")
    if num_frames < 2:
        raise ValueError(f"SyntheticWorld: num_frames={num_frames}; expected at least 2")
    rng = np.random.default_rng(seed)
    sched = _schedule(scenario, num_frames, rng)
    n = num_frames
    speed_k = np.zeros(n)
    lateral = np.full(n, LANE)
    yaw_off = np.zeros(n)
    base_speed = 0.9 + 0.3 * rng.random()
    legacy = speed is None and turn_rate is None and scenario != "city"
    first = 5.0
    if legacy:  # the default worlds, unchanged
        cruise, radius, v_turn, gap = base_speed, CORNER_RADIUS, math.inf, 20.0
    else:  # own stream: the rest of the world (traffic, layout draws) stays that of the seed
        prm = np.random.default_rng([seed, 271828])
        cruise = draw_speed(speed, CITY_SPEED if scenario == "city" else (base_speed, base_speed), prm)
        omega = math.radians(draw_speed(turn_rate, TURN_RATE_DEG, prm))
        radius = float(np.clip(cruise / omega + prm.uniform(-1.0, 2.0), *TURN_RADIUS))
        v_turn = min(omega * radius, math.sqrt(LATERAL * radius))
        gap = 20.0 + 15.0 * cruise  # longer blocks when driving faster
        if scenario == "city":  # a corner soon, then blocks of 10-30 m (+ 10 m per m/frame)
            first, gap = float(prm.uniform(2.0, 8.0)), float(prm.uniform(10.0, 30.0)) + 10.0 * cruise
    # per-frame step (applied between frame k-1 and k) and offsets
    for k, name in enumerate(sched):
        wobble = math.sin(0.37 * k + seed)
        if name in ("drive", "lane_out", "lane_in", "moving_car"):
            speed_k[k] = base_speed + 0.1 * wobble if legacy else cruise * (1.0 + 0.08 * wobble)
        elif name == "planar":
            speed_k[k] = min(0.5, cruise)
        if scenario == "rotation":
            yaw_off[k] = math.radians(20.0) * math.sin(2 * math.pi * k / 24.0)
    # lateral offsets and yaw offsets of the named manoeuvres
    planar_lat = PLANAR_LATERAL
    lat_now, yaw_now = LANE, 0.0
    runs = _runs(sched)
    for name, a, b in runs:
        m = b - a
        for j, k in enumerate(range(a, b)):
            f = (j + 1) / m
            if name == "lane_out":
                lat_now = LANE + (planar_lat - LANE) * 0.5 * (1 - math.cos(math.pi * f))
            elif name == "lane_in":
                lat_now = planar_lat + (LANE - planar_lat) * 0.5 * (1 - math.cos(math.pi * f))
            elif name == "rot_in":
                yaw_now = 0.5 * math.pi * f
            elif name == "rot_out":
                yaw_now = 0.5 * math.pi * (1 - f)
            elif name == "planar":
                lat_now = planar_lat + 0.4 * math.sin(math.pi * f)
                if scenario == "planar":
                    yaw_now = 0.5 * math.pi + math.radians(3.0) * math.sin(2 * math.pi * k / 10.0)
            lateral[k] = lat_now
            if scenario != "rotation":
                yaw_off[k] = yaw_now
    corners = _plan_corners(scenario, speed_k, runs, radius, v_turn, gap, first)
    s = _timing(speed_k, corners, radius, v_turn)
    route = Route(corners, float(s[-1]) + 200.0, radius)
    pos, theta = route.pose(s, lateral)
    poses = np.zeros((n, 4, 4))
    segments: list[str] = []
    for k in range(n):
        pitch = math.radians(0.4) * math.sin(s[k] / 3.1 + seed)
        roll = math.radians(0.3) * math.sin(s[k] / 4.3 + 2 * seed)
        poses[k] = yaw_pose(pos[k, 0], pos[k, 1], theta[k] + yaw_off[k], pitch, roll)
        label = {"lane_out": "drive", "lane_in": "drive", "rot_in": "rotation", "rot_out": "rotation"}.get(
            sched[k], sched[k])
        nxt = theta[min(k + 1, n - 1)]
        if label == "drive" and abs(nxt - theta[k]) > math.radians(0.5):
            label = "turn"
        segments.append(label)
    tracks, sizes, clear = _vehicles(route, s, sched, runs, rng, None if legacy else cruise)
    for name, a, b in runs:
        if name in ("planar", "lane_out", "lane_in", "rot_in", "rot_out", "still"):
            clear.append((s[a] - 15.0, s[b - 1] + 15.0, 1))
    return Trajectory(route, poses, segments, tracks, sizes, clear)


def _timing(step: np.ndarray, corners: list[float], radius: float, v_turn: float) -> np.ndarray:
    """Centre-line arc length (N,) of each frame. Default worlds: the cumulative scheduled steps. Otherwise the
    camera (in its lane, ``LANE`` to the right) travels the scheduled step (N,) along its own path, limited to
    ``sqrt(v_c^2 + 2 BRAKE d)`` at a centre-line distance d from a corner, where ``v_c`` is ``v_turn`` scaled to
    the camera's path radius there (``radius -+ LANE``; turns alternate right, left, ...)."""
    if not corners or not math.isfinite(v_turn):
        return np.cumsum(step) - step[0]
    c = np.asarray(corners)
    arc = 0.5 * math.pi * radius
    scale = (radius - LANE * np.where(np.arange(len(c)) % 2 == 0, 1.0, -1.0)) / radius  # camera / centre length
    s = np.zeros(len(step))
    for k in range(1, len(step)):
        v, here = step[k], s[k - 1]
        if v > 0:
            d = np.maximum(np.maximum(c - here, here - (c + arc)), 0.0)
            v = min(v, float(np.min(np.sqrt((v_turn * scale) ** 2 + 2.0 * BRAKE * d))))
        while v > 1e-12:  # walk the camera's path length v over lines and arcs
            on = np.nonzero((c <= here) & (here < c + arc))[0]
            ahead = c[c > here]
            if len(on):
                f, end = scale[on[0]], c[on[0]] + arc
            else:
                f, end = 1.0, ahead[0] if len(ahead) else math.inf
            if v <= (end - here) * f:
                here, v = here + v / f, 0.0
            else:
                v -= (end - here) * f
                here = end
        s[k] = here
    return s


def _protected(s: np.ndarray, runs: list[tuple[str, int, int]]) -> list[tuple[float, float]]:
    """Arc-length ranges where no corner may be: around the planar and moving_car manoeuvres."""
    out = [(s[a] - 6.0, s[b - 1] + 12.0) for name, a, b in runs if name == "planar"]
    return out + [(s[a] - 5.0, s[b - 1] + 10.0) for name, a, b in runs if name == "moving_car"]


def _plan_corners(scenario: str, step: np.ndarray, runs: list[tuple[str, int, int]], radius: float, v_turn: float,
                  gap: float, first: float) -> list[float]:
    """Corner positions of a drive or city: from ``first``, every ``arc + gap`` metres where no manoeuvre is
    protected. Braking for the corners moves the manoeuvres along the route, so placement and timing are
    iterated to agreement; a corner that still overlaps a manoeuvre is dropped."""
    if scenario not in ("drive", "city"):
        return []
    arc = 0.5 * math.pi * radius

    def place(s: np.ndarray) -> list[float]:
        protected = _protected(s, runs)
        corners: list[float] = []
        c = first
        while c < s[-1] + 5.0:
            if any(lo < c + arc and c < hi for lo, hi in protected) or (corners and c < corners[-1] + arc + gap):
                c += 1.0
                continue
            corners.append(c)
            c += arc + gap
        return corners

    corners = place(_timing(step, [], radius, v_turn))
    for _ in range(8):
        new = place(_timing(step, corners, radius, v_turn))
        if new == corners:
            break
        corners = new
    while True:
        protected = _protected(_timing(step, corners, radius, v_turn), runs)
        bad = [c for c in corners if any(lo < c + arc and c < hi for lo, hi in protected)]
        if not bad:
            return corners
        corners.remove(bad[0])


def _runs(sched: list[str]) -> list[tuple[str, int, int]]:
    runs = []
    a = 0
    for k in range(1, len(sched) + 1):
        if k == len(sched) or sched[k] != sched[a]:
            runs.append((sched[a], a, k))
            a = k
    return runs


def _vehicles(route: Route, s: np.ndarray, sched: list[str], runs: list[tuple[str, int, int]],
              rng: np.random.Generator, cruise: float | None) -> tuple[np.ndarray, np.ndarray, list]:
    """Oncoming cars in the left lane and, for each moving_car segment, a truck pulling out just ahead.
    ``cruise`` (m/frame; None for the default worlds) scales the oncoming speed and how many cars come."""
    n = len(s)
    k = np.arange(n)
    s_list, lat_list, yaw_flip, sizes = [], [], [], []
    v = 0.8 + 0.6 * rng.random()  # one speed for the column of oncoming cars: they never run into each other
    if cruise is None:
        num_oncoming = max(3, n // 15)  # keep oncoming traffic coming on long sequences
    else:
        v *= cruise / 1.05
        num_oncoming = max(3, math.ceil((s[-1] + v * n) / 35.0))
    for i in range(num_oncoming):
        s0 = 15.0 + 35.0 * i + 25.0 * rng.random()
        s_list.append(s0 - v * k)
        lat_list.append(np.full(n, -LANE))
        yaw_flip.append(math.pi)
        sizes.append([1.8, 1.5, 4.2])
    clear: list[tuple[float, float, int]] = []
    truck_runs = [(a, b) for name, a, b in runs if name == "moving_car"]
    for a, b in truck_runs:  # one truck per moving_car segment: parked ahead, pulls out in front of the camera
        gap0 = 2.4 + 4.0  # truck centre ahead of the camera (rear 2.4 m ahead, length 8 m)
        st = np.empty(n)
        lat = np.empty(n)
        st[: a + 1] = s[a] + gap0
        lat[: a + 1] = PARKING
        for kk in range(a + 1, n):
            rel = kk - a
            extra = 0.08 * rel if kk < b else 0.08 * (b - a) + 0.6 * (kk - b + 1)
            st[kk] = s[kk] + gap0 + extra
            lat[kk] = LANE + (PARKING - LANE) * max(0.0, 1.0 - rel / 4.0)
        s_list.append(st)
        lat_list.append(lat)
        yaw_flip.append(0.0)
        sizes.append([2.5, 3.2, 8.0])
        clear.append((s[a] - 30.0, s[a] + 30.0, 1))
    S = np.stack(s_list, 1)
    L = np.stack(lat_list, 1)
    pos, theta = route.pose(S, L)
    yaw = theta + np.array(yaw_flip)[None, :]
    present = np.ones_like(yaw)
    tracks = np.concatenate([pos, yaw[..., None], present[..., None]], -1)
    return tracks, np.array(sizes, dtype=np.float64), clear
