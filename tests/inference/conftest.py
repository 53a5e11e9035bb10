"""Fixtures of the inference tests: ``infer.py`` as a user runs it (in a folder of its own, so stray outputs show),
and frame folders made from the synthetic world."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


class InferCli:
    """Runs ``python REPO/infer.py ARGS`` with the working directory ``cwd`` (an empty folder of the test)."""

    def __init__(self, cwd: Path) -> None:
        self.cwd = cwd
        cwd.mkdir(parents=True, exist_ok=True)

    def args(self, *args: str) -> list[str]:
        return [sys.executable, str(REPO / "infer.py"), *args]

    def env(self) -> dict[str, str]:
        env = dict(os.environ, OMP_NUM_THREADS="1")
        env.pop("HYDRA_FULL_ERROR", None)
        return env

    def __call__(self, *args: str, check: bool = True, timeout: float = 300) -> subprocess.CompletedProcess:
        proc = subprocess.run(self.args(*args), cwd=self.cwd, capture_output=True, text=True, timeout=timeout,
                              env=self.env())
        if check and proc.returncode != 0:
            raise AssertionError(f"infer.py {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        return proc

    def popen(self, *args: str) -> subprocess.Popen:
        return subprocess.Popen(self.args(*args), cwd=self.cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env=self.env())


@pytest.fixture
def infer_cli(tmp_path: Path) -> InferCli:
    """``infer.py`` run from the empty folder ``tmp_path/cwd`` (assert ``not (cwd / "outputs").exists()``)."""
    return InferCli(tmp_path / "cwd")


@pytest.fixture(scope="module")
def module_infer_cli(tmp_path_factory: pytest.TempPathFactory) -> InferCli:
    """:func:`infer_cli` for a run shared by the tests of a module (its folder: ``module_infer_cli.cwd.parent``)."""
    return InferCli(tmp_path_factory.mktemp("shared_run") / "cwd")


def write_frames(folder: Path, images: Sequence[torch.Tensor]) -> Path:
    """(3,H,W) float [0,1] images as 8-bit PNGs ``000000.png, ...`` in ``folder`` (created)."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(images):
        arr = (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        Image.fromarray(arr).save(folder / f"{k:06d}.png")
    return folder


def intrinsics_overrides(K: torch.Tensor | np.ndarray) -> list[str]:
    """``data.fx= data.fy= data.cx= data.cy=`` of a (3,3) matrix."""
    K = np.asarray(K, dtype=np.float64)
    return [f"data.fx={K[0, 0]:.9g}", f"data.fy={K[1, 1]:.9g}", f"data.cx={K[0, 2]:.9g}", f"data.cy={K[1, 2]:.9g}"]


def read_kitti(path: Path) -> np.ndarray:
    """(N,4,4) poses of a KITTI pose file, asserting 12 numbers on every line."""
    rows = [line.split() for line in path.read_text().splitlines()]
    assert rows and all(len(r) == 12 for r in rows), f"{path}: every line must hold 12 numbers"
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    return T


@pytest.fixture(scope="session")
def frames_io() -> SimpleNamespace:
    """Helpers as attributes: ``write_frames``, ``intrinsics_overrides``, ``read_kitti``."""
    return SimpleNamespace(write_frames=write_frames, intrinsics_overrides=intrinsics_overrides, read_kitti=read_kitti)
