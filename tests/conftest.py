"""Shared test fixtures: the location of ../shared data (tests that need it skip when it is absent), the KITTI 00
trajectories of evo's tests, and ``infer.py`` as a user runs it (``infer_cli``: in a folder of its own, so stray
outputs show)."""

from __future__ import annotations

import contextlib
import io
import logging
import logging.config
import os
import subprocess
import sys
import traceback
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"

torch.set_num_threads(2)


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"needs {path} (the project's ../shared data folder); not present on this machine")
    return path


@pytest.fixture(autouse=True, scope="session")
def _runs_outside_the_repository(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Training runs and caches that a test does not place itself (train.py's default runs_dir) go to a temporary
    folder, never into the repository's runs/ (nor a developer's $DFVO_RUNS_DIR)."""
    saved = os.environ.get("DFVO_RUNS_DIR")
    os.environ["DFVO_RUNS_DIR"] = str(tmp_path_factory.mktemp("runs"))
    yield
    if saved is None:
        os.environ.pop("DFVO_RUNS_DIR", None)
    else:
        os.environ["DFVO_RUNS_DIR"] = saved


@pytest.fixture
def kitti_odom_root() -> Path:
    """``../shared/data/kitti_odom`` (sequence 06, frames 0-50, grayscale stereo, poses)."""
    return _require(SHARED_DATA / "kitti_odom" / "sequences" / "06").parents[1]


@pytest.fixture
def kitti_raw_root() -> Path:
    """``../shared/data/kitti_raw`` (drive 2011_09_26_0001, colour stereo JPEG, no oxts)."""
    return _require(SHARED_DATA / "kitti_raw" / "2011_09_26")


@pytest.fixture
def kitti_poses_full() -> Path:
    """``../shared/data/kitti_odom/poses_full`` (official GT poses 00-10)."""
    return _require(SHARED_DATA / "kitti_odom" / "poses_full")


KITTI00_EVO = SHARED_DATA / "trajectories" / "kitti00_evo"


@pytest.fixture(scope="session")
def kitti00() -> dict[str, Path]:
    """``{"gt", "times", "orb", "sptam"}``: KITTI 00 ground truth (4541 poses), its timestamps, and the ORB-SLAM
    and S-PTAM estimates, as published with evo's tests."""
    files = {"gt": "KITTI_00_gt.txt", "times": "KITTI_00_gt_times.txt", "orb": "KITTI_00_ORB.txt",
             "sptam": "KITTI_00_SPTAM.txt"}
    out = {k: KITTI00_EVO / v for k, v in files.items()}
    missing = [p for p in out.values() if not p.is_file()]
    if missing:
        pytest.skip(f"needs {missing[0]} (the project's ../shared data folder); not present on this machine")
    return out


@pytest.fixture(scope="session")
def kitti00_times(kitti00) -> np.ndarray:
    return np.loadtxt(kitti00["times"])


class ToolCli:
    """Runs ``python REPO/SCRIPT ARGS`` (``infer.py`` or ``train.py``) with the working directory ``cwd``.

    A call runs the command in this test process (the script's ``main`` with that ``sys.argv``, working directory,
    one torch thread, stdout/stderr captured, the exit status from ``SystemExit``; logging, Hydra, environment and
    random states restored afterwards): the same code path as the script, without 3-5 s of interpreter start and
    imports per call. ``in_subprocess=True`` (and every multirun, whose jobs are processes anyway) runs a real
    ``python SCRIPT`` instead; tests of signals use :meth:`popen`.
    """

    def __init__(self, cwd: Path, script: str = "infer.py") -> None:
        self.cwd, self.script = cwd, script
        cwd.mkdir(parents=True, exist_ok=True)

    def args(self, *args: str) -> list[str]:
        return [sys.executable, str(REPO_ROOT / self.script), *args]

    def env(self) -> dict[str, str]:
        env = dict(os.environ, OMP_NUM_THREADS="1")
        env.pop("HYDRA_FULL_ERROR", None)
        return env

    def __call__(self, *args: str, check: bool = True, timeout: float = 300,
                 in_subprocess: bool = False) -> subprocess.CompletedProcess:
        if in_subprocess or "-m" in args or "--multirun" in args:
            proc = subprocess.run(self.args(*args), cwd=self.cwd, capture_output=True, text=True, timeout=timeout,
                                  env=self.env())
        else:
            proc = self.in_process(*args)
        if check and proc.returncode != 0:
            raise AssertionError(f"{self.script} {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        return proc

    def in_process(self, *args: str) -> subprocess.CompletedProcess:
        """``SCRIPT ARGS`` run by this process (see the class docstring); global state restored afterwards."""
        import importlib
        import random

        from hydra.core.global_hydra import GlobalHydra

        cli = importlib.import_module(f"dfvo.cli.{Path(self.script).stem}")

        out, err = io.StringIO(), io.StringIO()
        saved_argv, saved_cwd, saved_env = sys.argv, os.getcwd(), dict(os.environ)
        saved_threads, root = torch.get_num_threads(), logging.getLogger()
        saved_handlers, saved_level = list(root.handlers), root.level
        saved_rng = random.getstate(), np.random.get_state(), torch.get_rng_state()
        code: int = 0
        try:
            os.chdir(self.cwd)
            sys.argv = [str(REPO_ROOT / self.script), *args]
            os.environ.clear()
            os.environ.update(self.env())  # the subprocess's environment, one thread included
            torch.set_num_threads(1)
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings(), \
                    _keeping_existing_log_handlers():
                warnings.simplefilter("default")  # each run shows its warnings, as a fresh process would
                try:
                    cli.main()
                except SystemExit as exc:
                    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                    if exc.code is not None and not isinstance(exc.code, int):
                        print(exc.code, file=sys.stderr)
                except BaseException:  # what the interpreter would print before exiting with 1
                    traceback.print_exc()
                    code = 1
        finally:
            for handler in root.handlers:
                if handler not in saved_handlers:
                    handler.close()
            root.handlers[:] = saved_handlers
            root.setLevel(saved_level)
            GlobalHydra.instance().clear()
            random.setstate(saved_rng[0])
            np.random.set_state(saved_rng[1])
            torch.set_rng_state(saved_rng[2])
            torch.set_num_threads(saved_threads)
            os.environ.clear()
            os.environ.update(saved_env)
            sys.argv = saved_argv
            os.chdir(saved_cwd)
        return subprocess.CompletedProcess(sys.argv[:1] + list(args), code, out.getvalue(), err.getvalue())

    def popen(self, *args: str) -> subprocess.Popen:
        return subprocess.Popen(self.args(*args), cwd=self.cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env=self.env())


@contextlib.contextmanager
def _keeping_existing_log_handlers() -> Iterator[None]:
    """Hydra configures logging with ``logging.config.dictConfig``, which closes every handler that exists (in a
    fresh process: none; here: pytest's capture handlers, which the next test would then write to). Within this
    context only the handlers created inside it are closed by a reconfiguration."""
    existing = {ref() for ref in logging._handlerList} - {None}
    original = logging.config._clearExistingHandlers

    def clear() -> None:
        logging._handlers.clear()
        logging.shutdown([ref for ref in logging._handlerList[:] if ref() not in existing])
        logging._handlerList[:] = [ref for ref in logging._handlerList if ref() in existing]

    logging.config._clearExistingHandlers = clear
    try:
        yield
    finally:
        logging.config._clearExistingHandlers = original


@pytest.fixture
def tool_cli() -> type[ToolCli]:
    """The :class:`ToolCli` runner itself: ``tool_cli(cwd, script)(*args)``."""
    return ToolCli


@pytest.fixture
def infer_cli(tmp_path: Path) -> ToolCli:
    """``infer.py`` run from the empty folder ``tmp_path/cwd`` (assert ``not (cwd / "outputs").exists()``)."""
    return ToolCli(tmp_path / "cwd")


@pytest.fixture
def train_cli(tmp_path: Path) -> ToolCli:
    """``train.py`` run from the empty folder ``tmp_path/train_cwd``."""
    return ToolCli(tmp_path / "train_cwd", "train.py")


@pytest.fixture(scope="module")
def module_train_cli(tmp_path_factory: pytest.TempPathFactory) -> ToolCli:
    """:func:`train_cli` for a run shared by the tests of a module."""
    return ToolCli(tmp_path_factory.mktemp("shared_train") / "cwd", "train.py")


@pytest.fixture(scope="module")
def module_infer_cli(tmp_path_factory: pytest.TempPathFactory) -> ToolCli:
    """:func:`infer_cli` for a run shared by the tests of a module (its folder: ``module_infer_cli.cwd.parent``)."""
    return ToolCli(tmp_path_factory.mktemp("shared_run") / "cwd")
