"""The typed settings of ``dfvo-eval task=flow|depth``: registered in Hydra's ConfigStore through the command's
schema, built on the inference dataclasses (not copies of them), with the defaults the YAML files had."""

from __future__ import annotations

import dataclasses

import pytest
from hydra import compose, initialize_config_module
from hydra.errors import HydraException
from omegaconf import OmegaConf

from dfvo.cli.evaluate import EvaluateConfig
from dfvo.source_eval.config import (
    DepthEvalConfig,
    FlowEvalConfig,
    FlowSelectionEvalConfig,
    task_settings,
)
from dfvo.sources.config import DepthSourceConfig, FlowSourceConfig
from dfvo.tracking.config import SelectionConfig


def _compose(*overrides: str):
    with initialize_config_module(config_module="dfvo.conf.evaluate", version_base="1.3"):
        return compose(config_name="evaluate", overrides=list(overrides))


def _declared_here(cls: type) -> set[str]:
    return set(vars(cls).get("__annotations__", {}))


def test_evaluate_command_is_typed_down_to_the_task_settings():
    cfg = _compose("task=flow", "flow.source=dis", "flow.preset=fast", "flow.selection.method=threshold",
                   "depth.network.depth_scale=5.4", "depth.crop=eigen")
    assert OmegaConf.get_type(cfg) is EvaluateConfig
    assert OmegaConf.get_type(cfg.flow) is FlowEvalConfig and OmegaConf.get_type(cfg.depth) is DepthEvalConfig
    flow, depth = task_settings(FlowEvalConfig, cfg, "flow"), task_settings(DepthEvalConfig, cfg, "depth")
    assert (flow.source, flow.preset, flow.selection.method) == ("dis", "fast", "threshold")
    assert depth.network.depth_scale == 5.4 and depth.crop == "eigen"


@pytest.mark.parametrize("override", ["flow.layout=kitti2020", "flow.bogus=1", "flow.selection.num=5",
                                      "depth.crop=middle", "depth.network.bogus=1", "flow.thresholds=three"])
def test_bad_task_settings_fail_when_composed(override: str):
    with pytest.raises(HydraException):
        _compose("task=flow", override)


def test_task_settings_reuse_the_inference_dataclasses_instead_of_copying_them():
    assert issubclass(FlowEvalConfig, FlowSourceConfig) and issubclass(FlowSelectionEvalConfig, SelectionConfig)
    # declared again only where the evaluation differs (documented in dfvo.source_eval.config)
    assert _declared_here(FlowEvalConfig) & {f.name for f in dataclasses.fields(FlowSourceConfig)} == \
        {"source", "refine"}
    assert _declared_here(FlowSelectionEvalConfig) & {f.name for f in dataclasses.fields(SelectionConfig)} == \
        {"method", "num_correspondences"}
    network = {f.name: f for f in dataclasses.fields(DepthEvalConfig)}["network"]
    assert network.type in (DepthSourceConfig, "DepthSourceConfig")
    assert not _declared_here(DepthEvalConfig) & ({f.name for f in dataclasses.fields(DepthSourceConfig)}
                                                  - {"source", "min_depth", "max_depth"})


def test_defaults_are_those_the_yaml_files_had():
    """The values of the former conf/evaluate/{flow,depth}/default.yaml (commit a81165a)."""
    flow, depth = FlowEvalConfig(), DepthEvalConfig()
    assert (flow.layout, flow.source, flow.checkpoint, flow.variant, flow.input_size, flow.preset) == \
        ("kitti2015", "auto", "checkpoints/flow.safetensors", None, None, "medium")
    assert (flow.working_size, flow.pred_bwd_dir, flow.fill_invalid, flow.frames, flow.max_pairs) == \
        (None, None, True, None, None)
    assert flow.thresholds == [1, 3, 5] and flow.device == "cpu" and flow.refine.iterations == 0
    sel = flow.selection
    assert (sel.method, sel.fraction, sel.num_correspondences, sel.max_inconsistency, sel.grid) == \
        ("best_n", 0.0163, None, 0.1, [10, 10])
    assert sel.num_for(192, 640) == 2003 and dataclasses.replace(sel, num_correspondences=7).num_for(192, 640) == 7
    net = depth.network
    assert (depth.split, depth.source, net.checkpoint, net.depth_scale, net.input_size, net.flip_average) == \
        (None, "auto", "checkpoints/depth.safetensors", 1.0, None, False)
    assert (net.min_depth, net.max_depth, depth.min_depth, depth.max_depth) == (0.1, 100.0, 1e-3, 80.0)
    assert (depth.crop, depth.median_scaling, depth.gt_pixel_offset, depth.max_frames, depth.device) == \
        ("garg", False, 0, None, "cpu")


def test_errors_name_the_key():
    with pytest.raises(ValueError, match=r"flow\.selection\.num: unknown setting; the settings of flow\.selection"):
        task_settings(FlowEvalConfig, {"flow": {"selection": {"num": 3}}}, "flow")
    with pytest.raises(ValueError, match=r"flow\.selection\.method='nope'"):
        task_settings(FlowEvalConfig, {"flow": {"selection": {"method": "nope"}}}, "flow")
    with pytest.raises(ValueError, match=r"depth\.min_depth=5\.0, depth\.max_depth=1\.0"):
        task_settings(DepthEvalConfig, {"depth": {"min_depth": 5, "max_depth": 1}}, "depth")
    with pytest.raises(ValueError, match=r"flow\.working_size=\[4, 4\]"):
        task_settings(FlowEvalConfig, {"flow": {"working_size": [4, 4]}}, "flow")
