"""The hand-held worlds: a camera held over a desk in the corner of two walls, or over a large print on a desk
(one plane fills the view), moved by hand.

What the street worlds cannot show: a scene of a few large planes (the desk, the back wall, the side wall) seen from
half a metre to two metres, and a motion without a car's inertia, in all six degrees of freedom: it speeds up, stops
dead for a few frames, and turns about every axis from one frame to the next (issue 40's hand-held and planar cases,
with exact truth; ``handheld_markers`` is the real one).

Convention (as :mod:`dfvo.synthetic.trajectory`): world x right, y down, z forward at the start; the desk top is the
ground plane ``y = CAMERA_HEIGHT``; the camera starts ``DESK_CLEARANCE`` above it, pitched down towards the corner.

- Motion: segments of 5-12 frames, each ``move`` (a new velocity, 1-6 cm a frame in a random direction, reached
  within two frames: a hand's jerk; half of them) or ``turn`` (a new rotation rate, up to 4 degrees a frame about
  each axis, with a little motion; a third), or of 3-6 frames ``still`` (no motion at all: a stop; a sixth). The
  camera stays in a box of +-0.35 m across, 0.3-0.8 m above the desk and +-0.3 m along (a velocity that would leave
  it is mirrored), its yaw within +-25 degrees, pitch 10-45 degrees down and roll within +-12 degrees (rates that
  would leave them are mirrored).
- Scene: the desk (a printed texture: papers and a blotter, grain down to millimetres), a back wall 1.6 m ahead and
  a side wall 0.9 m to the right, both covered in posters, and 4-7 books and boxes on the desk.
- Planar (``planar=True``, scenario ``handheld_planar``): the same motion with the camera pitched 40-80 degrees down
  (60 at the start), so that the desk alone fills the view (the view's top rays meet it within ~2 m), and a large
  print on the desk (``PRINT_HALF`` around ``PRINT_CENTRE``: colour blobs and sharp-edged shapes, as a printed
  poster or a pattern board); no walls and no objects: every pixel lies on one plane, the case where the essential
  matrix is degenerate and the homography explains the flow.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from dfvo.synthetic.scene import KIND_PRINT, Scene
from dfvo.synthetic.textures import band, fbm
from dfvo.synthetic.trajectory import CAMERA_HEIGHT, Route, Trajectory, yaw_pose

__all__ = ["DESK_CLEARANCE", "make_handheld_trajectory", "build_handheld_scene", "desk_ground", "PLANAR_PITCH_RANGE"]

DESK_CLEARANCE = 0.5  # the camera's start height above the desk, metres
BOX_ACROSS, BOX_ALONG, HEIGHT_RANGE = 0.35, 0.3, (0.3, 0.8)
YAW_LIMIT, PITCH_RANGE, ROLL_LIMIT = math.radians(25.0), (math.radians(-45.0), math.radians(-10.0)), \
    math.radians(12.0)
BACK_WALL_Z, SIDE_WALL_X = 1.6, 0.9
PLANAR_PITCH_RANGE, PLANAR_START_PITCH = (math.radians(-80.0), math.radians(-40.0)), math.radians(-60.0)
PRINT_CENTRE, PRINT_HALF = (0.0, 0.35), (0.9, 0.75)  # the planar world's print on the desk: centre and half size (x, z)


def make_handheld_trajectory(num_frames: int, seed: int, speed: float | tuple[float, float] | None = None,
                             planar: bool = False) -> Trajectory:
    """The hand-held motion (module docstring); ``speed``: the moving segments' speed in metres per frame, or a
    range to draw each segment's from (default 0.01-0.06); ``planar``: pitched down at the desk alone
    (``PLANAR_PITCH_RANGE``)."""
    rng = np.random.default_rng(seed + 4049)
    lo, hi = (0.01, 0.06) if speed is None else ((speed, speed) if isinstance(speed, (int, float)) else speed)
    pitch_range = PLANAR_PITCH_RANGE if planar else PITCH_RANGE
    pos = np.array([0.0, CAMERA_HEIGHT - DESK_CLEARANCE, 0.0])
    # yaw, pitch (negative: looking down), roll
    ang = np.array([0.0, PLANAR_START_PITCH if planar else math.radians(-28.0), 0.0])
    vel, rate = np.zeros(3), np.zeros(3)
    target_vel, target_rate = np.zeros(3), np.zeros(3)
    poses, names = [], []
    seg_left, seg = 0, "still"
    for _ in range(int(num_frames)):
        T = yaw_pose(pos[0], pos[2], ang[0], ang[1], ang[2])
        T[1, 3] = pos[1]
        poses.append(T)
        names.append("still" if seg == "still" else "handheld")
        if seg_left == 0:
            seg = str(rng.choice(["move", "move", "move", "still", "turn", "turn"]))
            seg_left = int(rng.integers(3, 7)) if seg == "still" else int(rng.integers(5, 13))
            if seg == "still":
                target_vel, target_rate = np.zeros(3), np.zeros(3)
            else:
                d = rng.normal(size=3) * np.array([1.0, 0.5, 1.0])
                s = float(rng.uniform(lo, hi)) * (0.3 if seg == "turn" else 1.0)
                target_vel = s * d / max(np.linalg.norm(d), 1e-9)
                target_rate = (rng.uniform(-1, 1, size=3) * math.radians(4.0) if seg == "turn"
                               else rng.uniform(-1, 1, size=3) * math.radians(0.8))
        seg_left -= 1
        if seg == "still":
            vel, rate = np.zeros(3), np.zeros(3)  # a stop is a stop
        else:
            vel = vel + 0.6 * (target_vel - vel)  # a jerk: most of the change within two frames
            rate = rate + 0.6 * (target_rate - rate)
        # stay in the box: a velocity or a rate that would leave it is mirrored
        nxt = pos + vel
        for i, (a, b) in enumerate(((-BOX_ACROSS, BOX_ACROSS),
                                    (CAMERA_HEIGHT - HEIGHT_RANGE[1], CAMERA_HEIGHT - HEIGHT_RANGE[0]),
                                    (-BOX_ALONG, BOX_ALONG))):
            if not a <= nxt[i] <= b:
                vel[i], target_vel[i] = -vel[i], -target_vel[i]
        pos = pos + vel
        nxt = ang + rate
        for i, (a, b) in enumerate(((-YAW_LIMIT, YAW_LIMIT), pitch_range, (-ROLL_LIMIT, ROLL_LIMIT))):
            if not a <= nxt[i] <= b:
                rate[i], target_rate[i] = -rate[i], -target_rate[i]
        ang = ang + rate
    n = len(poses)
    return Trajectory(route=Route([], 1.0), poses=np.stack(poses), segments=names,
                      tracks=np.zeros((n, 0, 4)), track_sizes=np.zeros((0, 3)), clear=[])


def desk_ground(seed: int):
    """Colour of the desk top (the ground plane) at world (x, z): a blotter with papers and grain to millimetres."""
    s = int(seed)
    rng = np.random.default_rng(s + 17)
    sheets = [(rng.uniform(-0.6, 0.6), rng.uniform(0.3, 1.4), rng.uniform(0.15, 0.3), rng.uniform(0.2, 0.35))
              for _ in range(5)]  # sheets of paper (centre x, z; width, height) with lines of writing

    def shade(x: torch.Tensor, z: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
        wood = fbm(x * 0.3, z * 4.0, s + 11, 0.4, 8, fp)  # grain along x
        speck = fbm(x, z, s + 13, 0.05, 5, fp)
        g = 0.25 + 0.35 * wood + 0.25 * (speck - 0.5)
        col = g[:, None] * torch.tensor([0.75, 0.55, 0.38], device=x.device)
        for cx, cz, w, h in sheets:
            sheet = band(x, cx - w / 2, cx + w / 2, fp) * band(z, cz - h / 2, cz + h / 2, fp)
            ink = band(torch.remainder(z - cz, 0.025), 0.006, 0.012, fp) \
                * (fbm(x * 3.0, z, s + 19, 0.03, 3, fp) > 0.5).float()
            paper = (0.88 - 0.6 * ink)[:, None] * torch.tensor([1.0, 0.99, 0.95], device=x.device)
            col = col * (1 - sheet[:, None]) + paper * sheet[:, None]
        return col

    return shade


def print_ground(seed: int):
    """Colour of the planar world's desk at world (x, z): the desk of :func:`desk_ground` with a large print
    (``PRINT_HALF`` around ``PRINT_CENTRE``): colour blobs from 1 cm to 10 cm, a grain down to millimetres and
    sharp-edged dark shapes."""
    s = int(seed)
    desk = desk_ground(seed)
    (cx, cz), (hx, hz) = PRINT_CENTRE, PRINT_HALF

    def shade(x: torch.Tensor, z: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
        inside = band(x, cx - hx, cx + hx, fp) * band(z, cz - hz, cz + hz, fp)
        colour = torch.stack([fbm(x, z, s + 31 + c, 0.1, 6, fp) for c in range(3)], -1)
        colour = 0.15 + 0.8 * ((colour - 0.5) * 2.0 + 0.5).clamp(0, 1)
        colour = colour * (0.7 + 0.6 * (fbm(x, z, s + 43, 0.015, 3, fp) - 0.5))[:, None]  # the print's fine grain
        # shapes: the level set of a coarse noise, its edge anti-aliased over the pixel footprint
        level = fbm(x, z, s + 37, 0.06, 2, fp) - 0.5
        ink = (level / (6.0 * fp.clamp_min(1e-4)) + 0.5).clamp(0, 1) * (fbm(x, z, s + 41, 0.2, 1, fp) > 0.5).float()
        colour = colour * (1.0 - 0.8 * ink[:, None])
        return desk(x, z, fp) * (1 - inside[:, None]) + colour * inside[:, None]

    return shade


def build_handheld_scene(traj: Trajectory, seed: int, planar: bool = False) -> Scene:
    """The desk, the two walls with posters and the objects on the desk (module docstring; deterministic); with
    ``planar``, the desk with its print alone (no boxes)."""
    if planar:
        return Scene(centre=np.zeros((0, 3)), yaw=np.zeros(0), half=np.zeros((0, 3)),
                     kind=np.zeros(0, dtype=np.int64), color=np.zeros((0, 3)), seed=np.zeros(0, dtype=np.int64),
                     num_dynamic=0, tracks=traj.tracks, ground=print_ground(seed))
    rng = np.random.default_rng(seed + 6007)
    rows: list[tuple] = []  # (centre xyz, yaw, half xyz, colour)
    top = CAMERA_HEIGHT  # the desk top
    rows.append(([0.0, top - 1.2, BACK_WALL_Z + 0.05], 0.0, [2.5, 1.2, 0.05], [0.85, 0.83, 0.78]))  # back wall
    rows.append(([SIDE_WALL_X + 0.05, top - 1.2, 0.5], 0.0, [0.05, 1.2, 1.5], [0.80, 0.82, 0.86]))  # side wall
    for _ in range(int(rng.integers(4, 8))):  # posters on the walls, a few mm proud of them
        w, h = rng.uniform(0.25, 0.6), rng.uniform(0.3, 0.7)
        if rng.random() < 0.6:
            x, y = rng.uniform(-1.2, SIDE_WALL_X - w / 2 - 0.05), top - rng.uniform(0.15 + h / 2, 1.6)
            rows.append(([x, y, BACK_WALL_Z - 0.003], 0.0, [w / 2, h / 2, 0.003], rng.uniform(0.3, 1.0, 3).tolist()))
        else:
            z, y = rng.uniform(-0.4, BACK_WALL_Z - w / 2 - 0.05), top - rng.uniform(0.15 + h / 2, 1.6)
            rows.append(([SIDE_WALL_X - 0.003, y, z], 0.0, [0.003, h / 2, w / 2], rng.uniform(0.3, 1.0, 3).tolist()))
    for _ in range(int(rng.integers(4, 8))):  # books and boxes on the desk
        half = [rng.uniform(0.05, 0.15), rng.uniform(0.01, 0.08), rng.uniform(0.07, 0.15)]
        x, z = rng.uniform(-0.6, SIDE_WALL_X - 0.2), rng.uniform(0.5, BACK_WALL_Z - 0.2)
        rows.append(([x, top - half[1], z], float(rng.uniform(-0.6, 0.6)), half, rng.uniform(0.2, 0.9, 3).tolist()))
    M = len(rows)
    return Scene(centre=np.array([r[0] for r in rows], dtype=np.float64),
                 yaw=np.array([r[1] for r in rows], dtype=np.float64),
                 half=np.array([r[2] for r in rows], dtype=np.float64),
                 kind=np.full(M, KIND_PRINT, dtype=np.int64),
                 color=np.array([r[3] for r in rows], dtype=np.float64),
                 seed=rng.integers(1 << 20, size=M).astype(np.int64),
                 num_dynamic=0, tracks=traj.tracks, ground=desk_ground(seed))
