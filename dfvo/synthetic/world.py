"""The synthetic world: one rendered sequence with exact depth, flow, stereo and poses (see :mod:`dfvo.synthetic`
for the conventions)."""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import numpy as np
import torch

from dfvo.geometry.camera import intrinsics_matrix, resize_intrinsics
from dfvo.synthetic.handheld import build_handheld_scene, make_handheld_trajectory
from dfvo.synthetic.highway import make_highway_trajectory
from dfvo.synthetic.highway_scene import build_highway_scene
from dfvo.synthetic.render import SKY_DEPTH, View, camera_rays, cast, flow_between
from dfvo.synthetic.scene import build_scene, rot_y
from dfvo.synthetic.shading import shade_views
from dfvo.synthetic.trajectory import HANDHELD_SCENARIOS, SCENARIOS, make_trajectory

__all__ = ["KITTI_K", "KITTI_HW", "SyntheticWorld"]

KITTI_K = (718.856, 718.856, 607.1928, 185.2157)
KITTI_HW = (376, 1241)


def _check_range(name: str, value: Any, lo: float, hi: float) -> None:
    """``value`` is None, a number in (lo, hi], or a pair lo < a <= b <= hi; else one line naming ``name``."""
    if value is None:
        return
    vals = list(value) if isinstance(value, (tuple, list)) else [value]
    ok = len(vals) in (1, 2) and all(isinstance(v, (int, float)) and lo < v <= hi for v in vals)
    if ok and len(vals) == 2:
        ok = vals[0] <= vals[1]
    if not ok:
        raise ValueError(f"SyntheticWorld: {name}={value!r}; expected None, a number in ({lo}, {hi}] or a range "
                         f"(lo, hi) with {lo} < lo <= hi <= {hi}")


class SyntheticWorld:
    """A rendered driving sequence with exact depth, flow, stereo and poses.

    Args:
        seed: world and trajectory seed (same seed, same pixels).
        num_frames: sequence length N (>= 2).
        height, width: output resolution (any size >= 8x8; intrinsics follow KITTI's ratios).
        baseline: stereo baseline b in metres (right camera = left translated by +b along x).
        exposure_change: vary the image gain smoothly from frame to frame (both cameras alike).
        noise_std: standard deviation of additive Gaussian sensor noise (images clamped to [0,1]).
        scenario: "drive" (mixed: drive, turn, still, rotation, planar, moving_car; see
            :meth:`segment_names`), one hard case alone: "still", "rotation", "planar", "moving_car",
            "straight" (driving without turns), "city" (streets with a corner every block), "highway"
            (motorway with traffic, ~2-3 m/frame), "handheld" (a camera moved by hand over a desk in the corner
            of two walls, 0.3-0.8 m above the desk: :mod:`dfvo.synthetic.handheld`) or "handheld_planar" (the same
            hand pitched down at a large print on the desk: one plane fills the view).
        speed: the camera's cruise speed in metres per frame, or a (lo, hi) range drawn per world (e.g.
            ``TRAINING_SPEED``). None: the scenario's default (street ~0.9-1.2, city ``CITY_SPEED``, highway
            ``HIGHWAY_SPEED``). On streets, setting it also draws the corner radius and turn rate (below) and
            the camera brakes for corners; the default worlds (speed and turn_rate None) are unchanged.
        turn_rate: street corners' yaw rate in degrees per frame, or a (lo, hi) range (default
            ``TURN_RATE_DEG`` = 5-10 once ``speed`` is set); ignored by "highway" (gentle curves).
        shadows: the objects cast shadows under the world's sun (:func:`~dfvo.synthetic.render.sun_shadowed`):
            shadowed road and facades, with the same depth and flow (default off: the worlds as they always were).
        device: where rendering runs and returned tensors live ("cpu", "cuda", ...; default CPU).
    """

    def __init__(self, seed: int = 0, num_frames: int = 100, height: int = 192, width: int = 640,
                 baseline: float = 0.54, exposure_change: bool = False, noise_std: float = 0.0,
                 scenario: str = "drive", speed: float | tuple[float, float] | None = None,
                 turn_rate: float | tuple[float, float] | None = None, shadows: bool = False,
                 device: str | torch.device | None = None) -> None:
        if height < 8 or width < 8:
            raise ValueError(f"SyntheticWorld: height={height}, width={width}; expected both >= 8 pixels")
        if baseline <= 0:
            raise ValueError(f"SyntheticWorld: baseline={baseline}; expected a positive stereo baseline in metres")
        if noise_std < 0:
            raise ValueError(f"SyntheticWorld: noise_std={noise_std}; expected >= 0")
        if scenario not in SCENARIOS:
            raise ValueError(f"SyntheticWorld: scenario={scenario!r}; expected one of {SCENARIOS}")
        _check_range("speed", speed, 0.0, 10.0)
        _check_range("turn_rate", turn_rate, 0.0, 30.0)
        self.seed = int(seed)
        self.height, self.width = int(height), int(width)
        self.baseline = float(baseline)
        self.exposure_change = bool(exposure_change)
        self.noise_std = float(noise_std)
        self.scenario = scenario
        self.shadows = bool(shadows)
        self.device = torch.device(device if device is not None else "cpu")
        if scenario == "highway":
            self._traj = make_highway_trajectory(int(num_frames), self.seed, speed)
            self._scene = build_highway_scene(self._traj, self.seed)
        elif scenario in HANDHELD_SCENARIOS:
            planar = scenario == "handheld_planar"
            self._traj = make_handheld_trajectory(int(num_frames), self.seed, speed, planar=planar)
            self._scene = build_handheld_scene(self._traj, self.seed, planar=planar)
        else:
            self._traj = make_trajectory(scenario, int(num_frames), self.seed, speed, turn_rate)
            self._scene = build_scene(self._traj, self.seed)
        K = intrinsics_matrix(*KITTI_K, batch_size=1)[0]
        self._K = resize_intrinsics(K, KITTI_HW, (self.height, self.width))
        self._rays = camera_rays(self._K, self.height, self.width, self.device)
        T = np.eye(4)
        T[0, 3] = self.baseline
        self._T_left_right = T
        self._views: OrderedDict[tuple[int, int], View] = OrderedDict()
        self._images: OrderedDict[tuple[int, int], torch.Tensor] = OrderedDict()

    def __len__(self) -> int:
        return len(self._traj.poses)

    # ----------------------------------------------------------------------------------------- accessors
    def poses(self) -> torch.Tensor:
        """(N,4,4) float64 left-camera poses ``T_w_c`` (float64 keeps relative motions exact far from origin)."""
        return torch.from_numpy(self._traj.poses.copy())

    def intrinsics(self) -> torch.Tensor:
        """(3,3) float32 intrinsics at (height, width), on the world's device."""
        return self._K.to(self.device, copy=True)

    def segment_names(self) -> list[str]:
        """Per-frame segment name: drive, turn, still, rotation, planar, moving_car, highway or handheld."""
        return list(self._traj.segments)

    def vehicle_poses(self, index: int) -> torch.Tensor:
        """(V,4,4) float64 ``T_w_o`` of the moving vehicles (box centre, yaw about +y) at frame ``index``."""
        index = self._check_index(index)
        centre, yaw = self._scene.box_poses(index)
        V = self._scene.num_dynamic
        T = np.tile(np.eye(4), (V, 1, 1))
        T[:, :3, :3] = rot_y(yaw[len(yaw) - V:])
        T[:, :3, 3] = centre[len(yaw) - V:]
        return torch.from_numpy(T)

    def vehicle_sizes(self) -> torch.Tensor:
        """(V,3) float64 full sizes of the moving vehicles' boxes along their own axes (width x, height y,
        length z), in the order of :meth:`vehicle_poses`."""
        return torch.from_numpy(2.0 * self._scene.half[len(self._scene.half) - self._scene.num_dynamic:])

    def T_right_left(self) -> torch.Tensor:
        """(4,4) float32 transform from the left to the right camera (translation (-b, 0, 0))."""
        return torch.from_numpy(np.linalg.inv(self._T_left_right)).float().to(self.device)

    # ----------------------------------------------------------------------------------------- rendering
    def _check_index(self, index: int) -> int:
        if not -len(self) <= index < len(self):
            raise IndexError(f"SyntheticWorld: frame index {index} out of range for a {len(self)}-frame sequence")
        return index % len(self)

    def _pose(self, index: int, cam: int) -> np.ndarray:
        T = self._traj.poses[index]
        return T @ self._T_left_right if cam == 1 else T

    def view(self, index: int, cam: int = 0) -> View:
        """Cast view of frame ``index`` for camera 0 (left) or 1 (right), cached (few most recent)."""
        index = self._check_index(index)
        if cam not in (0, 1):
            raise ValueError(f"SyntheticWorld: cam={cam}; expected 0 (left) or 1 (right)")
        key = (index, cam)
        if key in self._views:
            self._views.move_to_end(key)
            return self._views[key]
        v = cast(self._scene, index, self._pose(index, cam), self._K, self._rays, self.height, self.width)
        self._views[key] = v
        if len(self._views) > 6:
            self._views.popitem(last=False)
        return v

    def _gain(self, index: int) -> float:
        if not self.exposure_change:
            return 1.0
        return 1.0 + 0.18 * math.sin(0.45 * index + self.seed) + 0.07 * math.sin(1.7 * index + 3 * self.seed)

    def image(self, index: int, cam: int = 0) -> torch.Tensor:
        """(3,H,W) image of frame ``index``, left (cam 0) or right (cam 1), with exposure and noise applied."""
        return self.images(index, (cam,))[0]

    def images(self, index: int, cams: tuple[int, ...] = (0, 1)) -> list[torch.Tensor]:
        """Images (3,H,W) of frame ``index`` for cameras ``cams`` (0 left, 1 right); missing ones are shaded in
        one pass and cached (few most recent)."""
        index = self._check_index(index)
        todo = [c for c in cams if (index, c) not in self._images]
        if todo:
            shaded = shade_views(self._scene, [self.view(index, c) for c in todo], self.shadows)
            for cam, img in zip(todo, shaded, strict=True):
                g = self._gain(index)
                if g != 1.0:
                    img = (img * g).clamp(0, 1)
                if self.noise_std > 0:
                    gen = torch.Generator().manual_seed(self.seed * 1_000_003 + index * 2 + cam)
                    noise = torch.randn(img.shape, generator=gen).to(self.device)
                    img = (img + self.noise_std * noise).clamp(0, 1)
                self._images[(index, cam)] = img
        out = []
        for c in cams:
            self._images.move_to_end((index, c))
            out.append(self._images[(index, c)])
        while len(self._images) > 6:
            self._images.popitem(last=False)
        return out

    def depth(self, index: int) -> torch.Tensor:
        """(1,H,W) depth (z, metres) of the left image; sky = ``SKY_DEPTH``."""
        d = self.view(self._check_index(index)).depth
        return torch.where(torch.isfinite(d), d, torch.full_like(d, SKY_DEPTH))[None]

    def dynamic_mask(self, index: int) -> torch.Tensor:
        """(1,H,W) bool: left-image pixels of vehicles that move during the sequence."""
        ids = self.view(self._check_index(index)).ids
        first_dyn = len(self._scene.half) - self._scene.num_dynamic + 1
        return (ids >= first_dyn)[None]

    def object_kind(self, index: int) -> torch.Tensor:
        """(1,H,W) int64 what each left-image pixel of frame ``index`` shows: -1 sky, 0 the ground plane, else the
        material kind of its object (``KIND_*`` of :mod:`dfvo.synthetic.scene`: ``KIND_CAR`` for parked and moving
        cars alike, ``KIND_BUILDING``, ``KIND_POLE``, ...)."""
        ids = self.view(self._check_index(index)).ids
        kinds = torch.as_tensor(self._scene.kind, dtype=torch.int64, device=ids.device)
        return torch.where(ids > 0, kinds[(ids - 1).clamp_min(0)], ids.clamp_min(-1))[None]

    def flow(self, i: int, j: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact flow (2,H,W) from left image ``i`` to left image ``j`` and its validity (1,H,W) bool."""
        i, j = self._check_index(i), self._check_index(j)
        return flow_between(self._scene, self.view(i), self.view(j), self._rays)

    def render(self, index: int, right: bool = True, flow: bool = True) -> dict[str, torch.Tensor]:
        """All ground truth of frame ``index`` (keys per :mod:`dfvo.data`).

        Returns:
            dict with ``image`` (3,H,W), ``image_right`` (3,H,W) (if ``right``), ``depth`` (1,H,W),
            ``K`` (3,3), ``T_right_left`` (4,4), ``pose`` (4,4) float32 ``T_w_c``, ``dynamic_mask`` (1,H,W),
            ``index`` (); and for ``index < len-1`` (if ``flow``): ``flow_fwd`` (2,H,W) index->index+1 on
            image index, ``flow_bwd`` (2,H,W) index+1->index on image index+1, ``flow_fwd_valid``,
            ``flow_bwd_valid`` (1,H,W) bool.
        """
        index = self._check_index(index)
        imgs = self.images(index, (0, 1) if right else (0,))
        out = {
            "image": imgs[0],
            "depth": self.depth(index),
            "K": self.intrinsics(),
            "T_right_left": self.T_right_left(),
            "pose": torch.from_numpy(self._traj.poses[index]).float().to(self.device),
            "dynamic_mask": self.dynamic_mask(index),
            "index": torch.tensor(index, device=self.device),
        }
        if right:
            out["image_right"] = imgs[1]
        if flow and index < len(self) - 1:
            out["flow_fwd"], out["flow_fwd_valid"] = self.flow(index, index + 1)
            out["flow_bwd"], out["flow_bwd_valid"] = self.flow(index + 1, index)
        return out
