"""Synthetic driving worlds with exact ground truth: images, stereo, depth, optical flow, poses.

Street scenarios: a street with textured road, pavements, building rows, poles, parked and moving cars
(:mod:`dfvo.synthetic.trajectory`, :mod:`dfvo.synthetic.scene`). The highway scenario: a curving
dual carriageway with lanes, median barrier, guard rails, trees, signs, forest edges and distant hills, and
traffic at its own speeds (:mod:`dfvo.synthetic.highway`, :mod:`dfvo.synthetic.highway_scene`).
Rendered by ray casting in plain PyTorch on the CPU or a GPU (:mod:`dfvo.synthetic.render`), with
procedural textures evaluated on 3-D surface coordinates (:mod:`dfvo.synthetic.shading`,
:mod:`dfvo.synthetic.textures`). Everything is deterministic in ``seed`` (and the settings).

Modules: :mod:`dfvo.synthetic.world` (:class:`SyntheticWorld`), :mod:`dfvo.synthetic.datasets`
(datasets, held-out worlds). This module gathers their public names.

Held-out worlds: seeds >= ``HELD_OUT_SEED`` (1000) are evaluation worlds and are never trained on
(:func:`check_training_seeds`); :func:`held_out_worlds` lists the ones benchmarks use, per scenario.

Convention:
    - Images (3,H,W) float in [0,1]; depth (1,H,W) z in metres; flow (2,H,W) in pixels
      (``flow_i->j(x)`` = position in image j of the surface point seen at pixel x of image i, minus x);
      masks (1,H,W) bool; ``K`` (3,3) KITTI-like intrinsics at the working resolution
      (KITTI odometry ``fx = fy = 718.856``, ``cx = 607.1928``, ``cy = 185.2157`` at 1241x376, resized with
      :func:`dfvo.geometry.camera.resize_intrinsics`).
    - Poses ``T_w_c`` (4,4) of the left camera, world = first camera's axes (x right, y down, z forward);
      the camera stays 1.65 m above the road. ``T_right_left`` has translation (-b, 0, 0).
    - Sky is at infinity: its depth is reported as ``SKY_DEPTH`` (1000 m); its flow is the pure-rotation
      flow of a point at infinity (exact), but ``flow_*_valid`` is False there, because depth+pose do not
      reproduce it with a finite depth.
    - ``flow_*_valid`` is False where the point leaves the image (``u`` outside [0, W-1] or ``v`` outside
      [0, H-1]), falls behind the camera, or is hidden in the other frame by a nearer surface.
    - ``dynamic_mask`` marks pixels of vehicles that move during the sequence (oncoming cars, the truck,
      all highway traffic).
    - ``flow(i, j)`` is exact for any two frames (frame-skip pairs included): static points move with the
      camera, vehicle points with their vehicle's pose at frames i and j.
    - Tensors from a world are on its ``device``, except ``poses()`` and ``vehicle_poses()`` (CPU float64).
"""

from __future__ import annotations

from dfvo.synthetic.datasets import (
    HELD_OUT_SEED,
    HELD_OUT_SPEED,
    TRAINING_SCENARIOS,
    TRAINING_SPEED,
    HeldOutWorld,
    SyntheticFlowDataset,
    SyntheticSequenceDataset,
    check_training_seeds,
    held_out_worlds,
)
from dfvo.synthetic.highway import HIGHWAY_SPEED
from dfvo.synthetic.render import SKY_DEPTH
from dfvo.synthetic.trajectory import CAMERA_HEIGHT, CITY_SPEED, SCENARIOS, TURN_RATE_DEG
from dfvo.synthetic.world import KITTI_HW, KITTI_K, SyntheticWorld

__all__ = ["SKY_DEPTH", "SCENARIOS", "CAMERA_HEIGHT", "KITTI_K", "KITTI_HW", "HIGHWAY_SPEED", "CITY_SPEED",
           "TURN_RATE_DEG", "TRAINING_SPEED", "TRAINING_SCENARIOS", "HELD_OUT_SEED", "HELD_OUT_SPEED", "HeldOutWorld",
           "held_out_worlds", "check_training_seeds", "SyntheticWorld", "SyntheticSequenceDataset",
           "SyntheticFlowDataset"]
