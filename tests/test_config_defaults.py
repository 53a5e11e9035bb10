"""One home per setting: a public function whose parameter mirrors a config field has the field's default (or none).

Two checks, both by introspection so that a new drift fails without anyone updating this file:

- :data:`MIRRORS` pairs functions with the config dataclass they mirror; every parameter named like a field of that
  dataclass (or mapped to one in the pair's renames) must default to the field's default or have no default.
- :func:`test_no_parameter_default_contradicts_every_config_field` sweeps every public function and class of the
  package: a parameter with a literal default that is named like a config field must match the default of at least
  one field of that name (names such as ``min_points`` mean different things in different sections, so one match is
  enough), unless it is listed in :data:`UNRELATED` with the reason it is not a mirror.

Functions in a layer below their config's module (geometry, data, models, losses, eval) cannot take the default from
the dataclass (that import would point upwards); for them this test is the guard that keeps the literal equal.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
from collections.abc import Callable
from enum import Enum
from typing import Any

import pytest

import dfvo
from dfvo.cli.evaluate import EvaluateConfig
from dfvo.data.euroc import open_euroc
from dfvo.data.kitti_odometry import KittiOdometry
from dfvo.data.tum_rgbd import open_tum
from dfvo.eval.report import evaluate_sequences
from dfvo.geometry.gric import gric, gric_essential, gric_homography
from dfvo.geometry.pnp import PnPConfig, solve_pnp_ransac
from dfvo.geometry.two_view import EssentialConfig, find_essential_ransac, find_homography_ransac
from dfvo.inference.config import (
    EurocDataConfig,
    InferConfig,
    KittiOdomDataConfig,
    TensorboardConfig,
    TumDataConfig,
    ViewerConfig,
)
from dfvo.inference.loop import track_sequence
from dfvo.inference.outputs import fallback_summary
from dfvo.inference.rerun_observer import RerunObserver
from dfvo.inference.tb_logging import TensorboardObserver
from dfvo.inference.timing import StageTimer
from dfvo.io.association import associate_trajectories
from dfvo.losses.flow_losses import self_supervised_flow_loss
from dfvo.losses.photometric import ssim_l1_error
from dfvo.matching.pyramid_refinement import PyramidRefinementConfig, build_pyramid
from dfvo.matching.selection import SelectionConfig, select_correspondences
from dfvo.models.depth_net import DepthNet, disp_to_depth
from dfvo.sources.config import DepthSourceConfig, FlowSourceConfig
from dfvo.sources.dis import DISFlow
from dfvo.sources.networks import NetworkDepth
from dfvo.tracking.config import ModelSelectionConfig, RoadPlaneConfig, ScaleConfig, ScaleFilterConfig
from dfvo.tracking.ground_plane import fit_road_plane
from dfvo.tracking.scale import iterative_scale, sample_depth, simple_scale
from dfvo.tracking.scale_filter import ScaleFilter
from dfvo.tracking.temporal_scale import middle_depths, relative_scale
from dfvo.training.config import DepthModelConfig, FlowLossConfig
from dfvo.training.online_flow import OnlineFlowConfig

# (function or class, the config it mirrors, {parameter: field} for parameters named differently from their field)
MIRRORS: list[tuple[Callable[..., Any], type, dict[str, str]]] = [
    (select_correspondences, SelectionConfig, {"num": "num_correspondences"}),
    (find_essential_ransac, EssentialConfig, {}),
    (solve_pnp_ransac, PnPConfig, {}),
    (find_homography_ransac, ModelSelectionConfig, {"threshold_px": "h_threshold_px", "iterations": "h_iterations"}),
    (gric, ModelSelectionConfig, {"sigma": "gric_sigma"}),
    (gric_essential, ModelSelectionConfig, {"sigma": "gric_sigma"}),
    (gric_homography, ModelSelectionConfig, {"sigma": "gric_sigma"}),
    (sample_depth, ScaleConfig, {"crop_top": "depth_crop_top"}),
    (simple_scale, ScaleConfig, {"trials": "ransac_trials", "samples": "ransac_samples",
                                 "threshold": "inlier_threshold"}),
    (iterative_scale, ScaleConfig, {"max_iters": "iterative_max_iters", "tol": "iterative_tol",
                                    "flow_threshold_px": "iterative_flow_threshold_px"}),
    (fit_road_plane, RoadPlaneConfig, {}),
    (middle_depths, ScaleFilterConfig, {}),
    (relative_scale, ScaleFilterConfig, {}),
    (ScaleFilter, ScaleFilterConfig, {}),
    (build_pyramid, PyramidRefinementConfig, {}),
    (NetworkDepth, DepthSourceConfig, {}),
    (DISFlow, FlowSourceConfig, {}),
    (track_sequence, InferConfig, {}),
    (StageTimer, InferConfig, {}),
    (fallback_summary, InferConfig, {"threshold": "warn_fallback_rate"}),
    (TensorboardObserver, TensorboardConfig, {}),
    (RerunObserver, ViewerConfig, {}),
    (KittiOdometry, KittiOdomDataConfig, {}),
    (open_euroc, EurocDataConfig, {}),
    (open_tum, TumDataConfig, {}),
    (evaluate_sequences, EvaluateConfig, {}),
    (associate_trajectories, EvaluateConfig, {}),
    (self_supervised_flow_loss, FlowLossConfig, {"occ_alpha1": "", "occ_alpha2": ""}),
    (ssim_l1_error, DepthModelConfig, {}),
    (disp_to_depth, DepthModelConfig, {}),
    # init_depth: DepthNet(init_depth=None) builds a network without the initial-depth bias (inference loads its
    # weights); training passes model.init_depth
    (DepthNet, DepthModelConfig, {"init_depth": ""}),
    (self_supervised_flow_loss, OnlineFlowConfig, {"occ_alpha1": "", "occ_alpha2": ""}),
]

# (qualified name, parameter): why a parameter named like a config field of its subpackage is not its mirror
UNRELATED: dict[tuple[str, str], str] = {
    ("dfvo.geometry.essential_refine.refine_essential", "iterations"):
        "Levenberg-Marquardt steps of the local optimisation, not RANSAC samples",
    ("dfvo.geometry.two_view.find_homography_ransac", "iterations"):
        "the homography RANSAC's: ModelSelectionConfig.h_iterations (compared in MIRRORS)",
    ("dfvo.geometry.two_view.find_homography_ransac", "repeats"):
        "the homography RANSAC's repeats (no setting: one repeat), not the essential or PnP repeats",
    ("dfvo.tracking.gates.image_parallax_px", "quantile"):
        "the 90 % of the gates' stop test (gate.stop_flow_px), not the road plane's candidate share",
    ("dfvo.tracking.scale.simple_scale", "threshold"):
        "ScaleConfig.inlier_threshold (compared in MIRRORS), not the road plane's distance threshold",
    ("dfvo.training.sampling.ResumableLoader", "batch_size"): "a loader's own default; the data module passes "
                                                              "data.batch_size",
}


def _field_defaults(cls: type) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def _norm(value: Any) -> Any:
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, tuple | list):
        return [_norm(v) for v in value]
    return value


def _parameters(obj: Callable[..., Any]) -> dict[str, inspect.Parameter]:
    target = obj.__init__ if inspect.isclass(obj) else obj
    return dict(inspect.signature(target).parameters)


@pytest.mark.parametrize(("function", "config", "renames"), MIRRORS,
                         ids=[f"{f.__name__}-{c.__name__}" for f, c, _ in MIRRORS])
def test_function_defaults_are_the_config_defaults(function: Callable[..., Any], config: type,
                                                   renames: dict[str, str]) -> None:
    fields = _field_defaults(config)
    compared = 0
    for name, param in _parameters(function).items():
        field = renames.get(name, name)
        if not field or field not in fields:
            continue
        compared += 1
        if param.default is inspect.Parameter.empty:
            continue
        if param.default is None and dataclasses.is_dataclass(fields[field]):
            continue  # a section (a dataclass) passed as None means its defaults: a mutable default cannot be given
        assert _norm(param.default) == _norm(fields[field]), (
            f"{function.__qualname__}({name}={param.default!r}) but {config.__name__}.{field} defaults to "
            f"{fields[field]!r}: take the default from the dataclass (or give none)")
    assert compared, f"{function.__qualname__} mirrors no field of {config.__name__}: fix MIRRORS"


def _modules() -> list[Any]:
    names = [m.name for m in pkgutil.walk_packages(dfvo.__path__, "dfvo.")
             if ".conf" not in m.name and not m.name.endswith("__main__") and m.name != "dfvo.evaluate"]
    return [importlib.import_module(n) for n in sorted(names)]


def _subpackage(module_name: str) -> str:
    return module_name.split(".")[1]


def _config_classes(modules: list[Any]) -> list[type]:
    classes = {}
    for module in modules:
        for obj in vars(module).values():
            if dataclasses.is_dataclass(obj) and isinstance(obj, type) and obj.__name__.endswith("Config") and \
                    obj.__module__.startswith("dfvo."):
                classes[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return list(classes.values())


def _public_callables(modules: list[Any]) -> dict[str, Callable[..., Any]]:
    found: dict[str, Callable[..., Any]] = {}
    for module in modules:
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            if inspect.isfunction(obj) or (inspect.isclass(obj) and not dataclasses.is_dataclass(obj)):
                found[f"{module.__name__}.{obj.__qualname__}"] = obj
    return found


def test_no_parameter_default_contradicts_the_config_fields_of_its_subpackage() -> None:
    """A parameter with a literal default, named like a field of a config of the same subpackage (``dfvo.tracking``
    functions against the tracker's sections, ...), must match that field's default (one of them, when several
    sections share the name) or be listed in :data:`UNRELATED`. Functions mirroring a config of another subpackage
    are listed in :data:`MIRRORS`."""
    modules = _modules()
    by_name: dict[tuple[str, str], list[tuple[str, Any]]] = {}
    for cls in _config_classes(modules):
        for name, default in _field_defaults(cls).items():
            by_name.setdefault((_subpackage(cls.__module__), name), []).append((cls.__name__, _norm(default)))
    problems = []
    for qualname, obj in _public_callables(modules).items():
        try:
            params = _parameters(obj)
        except (TypeError, ValueError):  # builtins without a signature
            continue
        for name, param in params.items():
            fields = by_name.get((_subpackage(qualname), name))
            if not fields or param.default is inspect.Parameter.empty or param.default is None:
                continue
            if (qualname, name) in UNRELATED:
                continue
            if not any(_norm(param.default) == default for _, default in fields):
                problems.append(f"{qualname}({name}={param.default!r}); config fields: {fields}")
    assert not problems, "parameter defaults that match no config field of their name:\n" + "\n".join(problems)


def test_unrelated_entries_still_exist() -> None:
    """Each :data:`UNRELATED` entry names a parameter that still exists (a stale entry would hide a future one)."""
    found = _public_callables(_modules())
    for qualname, name in UNRELATED:
        assert qualname in found and name in _parameters(found[qualname]), f"stale UNRELATED entry {qualname}.{name}"


def test_the_example_drift_is_gone() -> None:
    """The drift the review found: PnP needed 6 rows by default where the tracker needs 10."""
    assert inspect.signature(solve_pnp_ransac).parameters["min_points"].default == PnPConfig().min_points == 10
