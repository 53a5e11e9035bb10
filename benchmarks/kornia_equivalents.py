"""Our geometry and image helpers against kornia's equivalents: same numbers?, shapes accepted, CPU time (one JSON).

For each helper that kornia also offers, on the batched float64 (geometry) or float32 (image) inputs the pipeline
uses: whether the outputs are bitwise equal, the largest difference, the process CPU time of each (1 thread, best of
7 rounds, so a shared machine's load matters less; ratios are what to read), and the facts that decide which one the
package uses (docs/geometry.md, "kornia equivalents"). Run:

    OMP_NUM_THREADS=1 python benchmarks/kornia_equivalents.py
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from kornia.filters import box_blur, spatial_gradient
from kornia.geometry import conversions as C
from kornia.geometry.camera import project_points as k_project_points
from kornia.geometry.camera import unproject_points
from kornia.geometry.epipolar import essential_from_Rt
from kornia.geometry.linalg import inverse_transformation

from dfvo.geometry.camera import backproject_points, project_points
from dfvo.geometry.essential_refine import essential_from_rt, skew, so3_exp
from dfvo.geometry.se3 import se3_inverse
from dfvo.geometry.two_view import normalise_points
from dfvo.matching.flow_warp import normalise_pixels
from dfvo.matching.image_ops import box_mean, gradient


def cpu_us(f: Callable[[], Any], n: int = 30, rounds: int = 7) -> float:
    f()
    best = float("inf")
    for _ in range(rounds):
        start = time.process_time()
        for _ in range(n):
            f()
        best = min(best, (time.process_time() - start) / n * 1e6)
    return best


def compare(ours: Callable[[], torch.Tensor], theirs: Callable[[], torch.Tensor], **facts: Any) -> dict[str, Any]:
    a, b = ours(), theirs()
    t_ours, t_kornia = cpu_us(ours), cpu_us(theirs)
    return {"bitwise_equal": bool(torch.equal(a, b)), "max_abs_diff": float((a - b).abs().max()),
            "cpu_us_ours": round(t_ours, 1), "cpu_us_kornia": round(t_kornia, 1),
            "kornia_time_ratio": round(t_kornia / t_ours, 2), **facts}


def accepts(f: Callable[[], Any]) -> bool:
    try:
        f()
    except (ValueError, RuntimeError, TypeError):
        return False
    return True


def main() -> None:
    torch.set_num_threads(1)
    torch.manual_seed(0)
    f64 = torch.float64
    out: dict[str, Any] = {"torch_threads": 1}

    v = torch.randn(4096, 3, dtype=f64)
    out["skew vs vector_to_skew_symmetric_matrix"] = compare(
        lambda: skew(v), lambda: C.vector_to_skew_symmetric_matrix(v),
        kornia_accepts_P_K_3=accepts(lambda: C.vector_to_skew_symmetric_matrix(torch.randn(4, 2, 3))))

    w = torch.randn(4096, 3, dtype=f64) * 0.05
    tiny = torch.randn(4096, 3, dtype=f64) * 1e-7
    W = skew(tiny)
    series = torch.eye(3, dtype=f64) + W + 0.5 * W @ W  # exact to ~1e-21 at these angles
    out["so3_exp vs axis_angle_to_rotation_matrix"] = compare(
        lambda: so3_exp(w), lambda: C.axis_angle_to_rotation_matrix(w),
        tiny_angle_error_ours=float((so3_exp(tiny) - series).abs().max()),
        tiny_angle_error_kornia=float((C.axis_angle_to_rotation_matrix(tiny) - series).abs().max()))

    R = C.axis_angle_to_rotation_matrix(torch.randn(256, 3, dtype=f64) * 0.1)
    t = F.normalize(torch.randn(256, 3, dtype=f64), dim=-1)
    eye, zero = torch.eye(3, dtype=f64).expand(256, 3, 3), torch.zeros(256, 3, 1, dtype=f64)
    out["essential_from_rt vs essential_from_Rt"] = compare(
        lambda: essential_from_rt(R, t), lambda: essential_from_Rt(eye, zero, R, t[..., None]),
        note="kornia's takes two absolute poses and composes the relative motion first")

    T = torch.eye(4, dtype=f64).repeat(256, 1, 1)
    T[:, :3, :3], T[:, :3, 3] = R, t
    out["se3_inverse vs inverse_transformation"] = compare(
        lambda: se3_inverse(T), lambda: inverse_transformation(T),
        kornia_accepts_A_B_4_4=accepts(lambda: inverse_transformation(T.reshape(16, 16, 4, 4))))

    pix = torch.rand(8, 20000, 2, dtype=f64) * torch.tensor([639.0, 191.0], dtype=f64)
    out["normalise_pixels vs normalize_pixel_coordinates"] = compare(
        lambda: normalise_pixels(pix, 192, 640), lambda: C.normalize_pixel_coordinates(pix, 192, 640))

    K = torch.tensor([[718.856, 0, 607.19], [0, 718.856, 185.21], [0, 0, 1]], dtype=f64).expand(8, 3, 3)
    X = torch.randn(8, 20000, 3, dtype=f64)
    X[..., 2] = X[..., 2].abs() * 20 + 1
    at_camera = torch.tensor([[[0.5, 0.2, 0.0]]], dtype=f64)  # a point in the camera's plane (z = 0)
    out["project_points vs kornia project_points"] = compare(
        lambda: project_points(X, K)[0], lambda: k_project_points(X, K[:, None]),
        z0_pixel_ours=project_points(at_camera, K[:1])[0][0, 0].tolist(),
        z0_pixel_kornia=k_project_points(at_camera, K[:1, None])[0, 0].tolist())

    depth = X[..., 2]
    out["backproject_points vs unproject_points"] = compare(
        lambda: backproject_points(pix, depth, K), lambda: unproject_points(pix, depth[..., None], K[:, None]))

    K_skew = K.clone()
    K_skew[:, 0, 1] = 2.0
    exact = (torch.linalg.inv(K_skew)[:, None] @ torch.cat([pix, torch.ones_like(pix[..., :1])], -1)[..., None])
    exact = exact[..., :2, 0]
    out["normalise_points vs normalize_points_with_intrinsics"] = compare(
        lambda: normalise_points(pix, K), lambda: C.normalize_points_with_intrinsics(pix, K[:, None]),
        skew_2px_error_ours=float((normalise_points(pix, K_skew) - exact).abs().max()),
        skew_2px_error_kornia=float((C.normalize_points_with_intrinsics(pix, K_skew[:, None]) - exact).abs().max()))

    grey = torch.rand(8, 1, 192, 640)
    out["gradient vs spatial_gradient(mode=diff)"] = compare(
        lambda: gradient(grey), lambda: spatial_gradient(grey, mode="diff")[:, 0])

    x = torch.rand(8, 3, 192, 640) * 100 + 300  # running sums of large values: where float32 precision shows
    exact_box = F.avg_pool2d(F.pad(x.double(), (5, 5, 5, 5), mode="replicate"), 11, stride=1)
    kornia_box = box_blur(x, (11, 11), border_type="replicate")
    out["box_mean vs box_blur"] = compare(
        lambda: box_mean(x, 11), lambda: box_blur(x, (11, 11), border_type="replicate"),
        error_vs_float64_ours=float((box_mean(x, 11).double() - exact_box).abs().max()),
        error_vs_float64_kornia=float((kornia_box.double() - exact_box).abs().max()))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
