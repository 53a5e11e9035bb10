"""The typed training config: every YAML file is its schema plus the diff, typos and bad values fail in one line, data
roots come from data.root or an environment variable (never the repository layout)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from dfvo.training import config as C
from dfvo.training.datamodule import DFVODataModule

REPO = Path(__file__).resolve().parents[2]
CONF = REPO / "dfvo" / "conf" / "train"
SCHEMAS = {"model": C.MODEL_SCHEMAS, "data": C.TRAIN_DATA_SCHEMAS, "trainer": {"trainer": C.TrainerConfig}}
SHARED = REPO.parent / "shared" / "data"


def _compose(*overrides: str):
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        return compose("train", overrides=list(overrides))


def _raw(group: str, name: str) -> dict:
    return yaml.safe_load((CONF / group / f"{name}.yaml").read_text()) or {}


def _base(group: str, name: str):
    """What the defaults list of ``group/name.yaml`` gives, without the file's own keys."""
    node = OmegaConf.create()
    for entry in _raw(group, name)["defaults"]:
        if entry == "_self_":
            continue
        if entry.startswith(("schema/", "train_schema/")):
            node = OmegaConf.merge(node, OmegaConf.structured(SCHEMAS[group][entry.split("/")[1].split("@")[0]]))
        else:
            node = OmegaConf.merge(node, _full(group, entry))
    return node


def _full(group: str, name: str):
    return OmegaConf.merge(_base(group, name), {k: v for k, v in _raw(group, name).items() if k != "defaults"})


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


@pytest.mark.parametrize("group", ["model", "data", "trainer"])
def test_every_yaml_is_a_schema_plus_only_the_diff(group: str) -> None:
    """Each group file names a schema (or a sibling) in its defaults and sets only values that differ from it."""
    names = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
    assert names
    for name in names:
        raw, text = _raw(group, name), (CONF / group / f"{name}.yaml").read_text()
        if text.startswith("# @package _global_"):  # a preset reaching other groups (trainer=smoke): vs the schemas
            base = OmegaConf.structured(C.TrainConfig(trainer=C.TrainerConfig(), data=C.SyntheticTrainDataConfig()))
            assert set(raw) <= {"trainer", "data"}, f"{group}/{name}.yaml"
        else:
            assert raw.get("defaults", [None])[-1] == "_self_", f"{group}/{name}.yaml: defaults must end with _self_"
            base = _base(group, name)
        base = OmegaConf.create(OmegaConf.to_container(base, enum_to_str=True))
        for key, value in _flat({k: v for k, v in raw.items() if k != "defaults"}).items():
            assert OmegaConf.select(base, key) != value, f"{group}/{name}.yaml repeats {key}={value}"
        assert "shared" not in text and "${dfvo_repo" not in text, f"{group}/{name}.yaml assumes the repo layout"


def test_training_and_inference_schemas_coexist_in_one_process() -> None:
    """Both entry points register data schemas in Hydra's one ConfigStore; registering the inference ones last must
    not change what the training config composes into (nor the reverse). Seen in CI: the training data nodes had
    become the inference dataclasses, whatever registered last."""
    from dfvo.inference.config import KittiRawDataConfig as InferKittiRaw
    from dfvo.inference.config import register_configs as register_infer

    C.register_configs()
    register_infer()
    cfg = _compose("data=kitti_raw", "data.height=64")
    assert OmegaConf.get_type(cfg.data) is C.KittiRawTrainDataConfig and cfg.data.height == 64
    with initialize_config_module("dfvo.conf.infer", version_base="1.3"):
        assert OmegaConf.get_type(compose("infer", overrides=["data=kitti_raw"]).data) is InferKittiRaw
    assert InferKittiRaw.__name__ != C.KittiRawTrainDataConfig.__name__  # two families, two names, one discriminator
    assert (cfg.data.kind, InferKittiRaw.kind) == ("kitti_raw", "kitti_raw")


def test_groups_compose_into_their_schemas() -> None:
    cfg = _compose("model=depth_mono_sc", "data=kitti_raw", "trainer=gpu")
    assert OmegaConf.get_type(cfg.model) is C.DepthModelConfig and OmegaConf.get_type(cfg.trainer) is C.TrainerConfig
    assert OmegaConf.get_type(cfg.data) is C.KittiRawTrainDataConfig
    m = C.model_config(cfg)
    assert (m.name, m.stereo, m.w_consistency, m.monitor) == ("depth_mono_sc", False, 5.0, "val/abs_rel_med")
    t = C.typed(cfg.trainer)
    assert (t.precision, t.channels_last, t.accelerator, t.max_epochs) == ("bf16-mixed", True, "gpu", 20)
    assert cfg.name == "depth_mono_sc_kitti_raw"
    ddp, smoke = C.typed(_compose("trainer=ddp").trainer), C.typed(_compose("trainer=smoke").trainer)
    assert ddp.strategy == "ddp" and ddp.max_epochs == 20
    assert (smoke.max_steps, smoke.limit_val_batches, smoke.validate_at_stop) == (3, 1, True) and smoke.export_weights
    smoke_data = C.data_config(_compose("trainer=smoke", "data=kitti_raw", "data.width=640"))  # the command line wins
    assert (smoke_data.batch_size, smoke_data.height, smoke_data.width) == (2, 64, 640)
    flow = C.model_config(_compose("model=flow_self"))
    assert (flow.mode, flow.lr, flow._target_) == (C.FlowMode.self, 1e-5, "dfvo.training.flow_module.FlowModule")
    for kind, schema in C.TRAIN_DATA_SCHEMAS.items():
        assert isinstance(C.data_config(_compose(f"data={kind}")), schema)


def test_typos_and_bad_values_fail_in_one_line() -> None:
    with pytest.raises(Exception, match="w_smoth"):
        _compose("model.w_smoth=1")
    with pytest.raises(Exception, match="frame_skip"):
        _compose("model=flow_supervised", "data=flyingchairs", "data.frame_skips=[2]")  # pair datasets have no gaps
    for overrides, message in [(["model.lr=-1"], "model.lr=-1.0; expected > 0"),
                               (["model=flow_self", "model.variant=huge"], "model.variant='huge'"),
                               (["data.frame_skips=[0]"], r"data.frame_skips=\[0\]; expected"),
                               (["data.seeds=[1000]"], r"data.seeds: seeds \[1000\] are held-out"),
                               (["model=depth_mono", "model.temporal=false"], "model.stereo / model.temporal")]:
        with pytest.raises(ValueError, match=message) as err:
            DFVODataModule(_compose(*overrides))
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="trainer.precision='fp8'; expected one of"):
        C.typed(_compose("trainer.precision=fp8").trainer)


def test_cfg_job_prints_every_default() -> None:
    res = subprocess.run([sys.executable, "train.py", "model=depth_stereo", "--cfg", "job"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    for line in ("_target_: dfvo.training.depth_module.DepthPoseModule", "w_smooth: 0.001", "flip_prob: 0.5",
                 "frame_skips:", "precision: auto", "channels_last: false", "validate_at_stop: true"):
        assert line in res.stdout, line


def test_data_root_from_data_root_or_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, train_cli) -> None:
    """Without data.root and its environment variable: one line saying how to set them (from the CLI too, with no
    traceback); with the variable: the dataset under it is read."""
    for kind, env in [("kitti_raw", "DFVO_KITTI_RAW_ROOT"), ("kitti_odom", "DFVO_KITTI_ODOM_ROOT"),
                      ("flyingchairs", "DFVO_FLYINGCHAIRS_ROOT"), ("kitti_flow", "DFVO_KITTI_FLOW_ROOT")]:
        monkeypatch.delenv(env, raising=False)
        model = "model=flow_supervised" if kind in ("flyingchairs", "kitti_flow") else "model=depth_stereo"
        dm = DFVODataModule(_compose(model, f"data={kind}"))
        with pytest.raises(ValueError, match=rf"^data={kind} needs the dataset folder: set the environment variable "
                                             rf"{env}=ROOT once or pass data.root=ROOT$"):
            dm.setup("fit")
    res = train_cli("data=kitti_raw", f"runs_dir={tmp_path}", check=False)  # (the variable is unset above)
    assert res.returncode == 1
    assert res.stderr.strip().splitlines()[-1].startswith(
        "dfvo-train: error: data=kitti_raw needs the dataset folder: set the environment variable DFVO_KITTI_RAW_ROOT")
    assert "Traceback" not in res.stderr
    raw = SHARED / "kitti_raw"
    if not raw.is_dir():
        pytest.skip(f"needs {raw} (the project's ../shared data folder)")
    monkeypatch.setenv("DFVO_KITTI_RAW_ROOT", str(raw))
    dm = DFVODataModule(_compose("model=depth_stereo", "data=kitti_raw", "data.val_seeds=[]"))
    dm.setup("fit")
    assert len(dm.train_set) > 0 and {"image", "image_prev", "image_right"} <= set(dm.train_set[0])
    chairs = SHARED / "flow_samples" / "FlyingChairs_release"
    if chairs.is_dir():
        monkeypatch.setenv("DFVO_FLYINGCHAIRS_ROOT", str(chairs))
        dm = DFVODataModule(_compose("model=flow_supervised", "data=flyingchairs"))
        dm.setup("fit")
        assert len(dm.train_set) > 0 and "flow_fwd" in dm.train_set[0]
