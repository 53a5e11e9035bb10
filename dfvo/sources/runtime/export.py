"""Export the flow and depth networks to ONNX from their checkpoints, with a record of what they were made from.

An exported model is only ever produced here, from the weights file a source loads (never downloaded). Its ONNX
metadata (``metadata_props``) records :meth:`ExportSpec.metadata`: the checkpoint's file name and sha256, the
network and its settings (FlowNet variant; the depth range), the input size, the ONNX opset, this module's export
format and the sha256 of the source files that define the exported graph. :func:`exported_model` returns the cached
export of a spec, exporting it first when the cache has none or holds one whose record differs from the spec (a
stale export: other weights, settings or network code), so a stale model is never used.

Command line (the same export a source makes on first use; prints the exported file):

    python -m dfvo.sources.runtime flow [--checkpoint checkpoints/flow.safetensors] [--input-size 96 320]
        [--cache-dir DIR]
    python -m dfvo.sources.runtime depth [--checkpoint checkpoints/depth.safetensors] [--cache-dir DIR]

Convention: the exported graphs are batch-first with a free batch size; images (B,3,h,w) in [0,1] at the network's
input size; flow (B,2,h,w) in pixels of that size (forward and backward, ``FlowNet.forward_backward``); depth
(B,1,h,w) in the network's units (``DepthNet.depth``; the source multiplies by ``depth_scale``).
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import logging
import os
import sys
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

__all__ = ["EXPORT_FORMAT", "OPSET", "ExportSpec", "FlowGraph", "DepthGraph", "default_cache_dir",
           "read_metadata", "stale_fields", "export_onnx", "exported_model"]

log = logging.getLogger("dfvo.sources.runtime")

EXPORT_FORMAT = "1"
"""Version of what :func:`export_onnx` writes (inputs, outputs, metadata); part of every export's record."""
OPSET = 18


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _code_sha256(network: str) -> str:
    """sha256 of the source files that define the exported graph of ``network`` (a change re-exports)."""
    from dfvo.geometry import camera
    from dfvo.matching import flow_warp
    from dfvo.models import correlation, depth_net, flow_net, resnet

    modules = (flow_net, correlation, flow_warp, camera) if network == "flow" else (depth_net, resnet)
    digest = hashlib.sha256()
    for module in (*modules, sys.modules[__name__]):
        digest.update(Path(inspect.getsourcefile(module)).read_bytes())
    return digest.hexdigest()


@dataclass(frozen=True)
class ExportSpec:
    """What an export is made from and how.

    Attributes:
        network: ``"flow"`` (FlowNet, forward and backward flow) or ``"depth"`` (DepthNet).
        checkpoint: the weights file the network was loaded from.
        input_size: (h, w) the network runs at (depth: multiples of 32; FlowNet resizes inside its graph).
        variant: FlowNet variant (flow only).
        min_depth, max_depth: the depth range (depth only).
    """

    network: str
    checkpoint: Path
    input_size: tuple[int, int]
    variant: str | None = None
    min_depth: float | None = None
    max_depth: float | None = None

    def __post_init__(self) -> None:
        if self.network not in ("flow", "depth"):
            raise ValueError(f"ExportSpec.network={self.network!r}; expected 'flow' or 'depth'")
        h, w = self.input_size
        if self.network == "depth" and (h % 32 or w % 32):
            raise ValueError(f"depth: export input size {h}x{w}; expected multiples of 32")

    def metadata(self) -> dict[str, str]:
        """The record written into the exported model (and compared on every later use)."""
        settings = ({"variant": str(self.variant)} if self.network == "flow"
                    else {"min_depth": repr(float(self.min_depth)), "max_depth": repr(float(self.max_depth))})
        return {"dfvo_export_format": EXPORT_FORMAT, "network": self.network, "opset": str(OPSET),
                "checkpoint_name": self.checkpoint.name, "checkpoint_sha256": _sha256(self.checkpoint),
                "input_size": f"{self.input_size[0]}x{self.input_size[1]}", **settings,
                "code_sha256": _code_sha256(self.network)}

    def file_name(self) -> str:
        """Cache file name: network, variant, the checkpoint's name and a hash of its absolute path, the input size.
        The same checkpoint file retrained in place maps to the same name (its old export is then stale and
        replaced); two checkpoints of the same name in different folders do not share one."""
        extra = f"-{self.variant}" if self.network == "flow" else ""
        where = hashlib.sha256(str(self.checkpoint.resolve()).encode()).hexdigest()[:10]
        return f"{self.network}{extra}-{self.checkpoint.stem}-{where}-{self.input_size[0]}x{self.input_size[1]}.onnx"


class FlowGraph(nn.Module):
    """The exported flow graph: ``FlowNet.forward_backward`` at the network's input size (see module docstring)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.net.forward_backward(img1, img2)


class DepthGraph(nn.Module):
    """The exported depth graph: ``DepthNet.depth`` (batch norms folded into the encoder, scale-0 head only)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        from dfvo.models.depth_net import fold_batch_norms

        self.encoder = fold_batch_norms(net.encoder)
        self.decoder = net.decoder
        self.min_depth, self.max_depth = float(net.min_depth), float(net.max_depth)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        from dfvo.models.depth_net import disp_to_depth

        disp = self.decoder(self.encoder(image), scales=(0,))[0]
        return disp_to_depth(disp, self.min_depth, self.max_depth)


def default_cache_dir() -> Path:
    """``$DFVO_CACHE_DIR/runtime``, else ``~/.cache/dfvo/runtime``."""
    root = os.environ.get("DFVO_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "dfvo") / "runtime"


def read_metadata(path: Path) -> dict[str, str]:
    """The ``metadata_props`` of an ONNX file (empty when it has none)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


def stale_fields(found: dict[str, str], expected: dict[str, str]) -> list[str]:
    """The record fields in which an exported model's metadata ``found`` differs from ``expected``."""
    return [k for k in expected if found.get(k) != expected[k]]


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence the exporter's progress lines and warnings (torch.onnx, onnxscript's optimiser, onnx_ir)."""
    names = ("torch.onnx", "torch._export", "torch.export", "onnxscript", "onnx_ir")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def export_onnx(net: nn.Module, spec: ExportSpec, path: Path, metadata: dict[str, str] | None = None) -> Path:
    """Export ``net`` (a loaded FlowNet or DepthNet, per ``spec.network``) to ONNX at ``path`` with the record of
    ``spec`` in its metadata. Written to a temporary file and renamed: a reader never sees half a model."""
    import onnx

    metadata = metadata or spec.metadata()
    graph = (FlowGraph(net) if spec.network == "flow" else DepthGraph(net)).eval()
    h, w = spec.input_size
    batch = torch.export.Dim("batch", min=1, max=256)
    if spec.network == "flow":
        example = (torch.rand(2, 3, h, w), torch.rand(2, 3, h, w))
        names, outputs = ["img1", "img2"], ["flow_fwd", "flow_bwd"]
        dynamic = {"img1": {0: batch}, "img2": {0: batch}}
    else:
        example = (torch.rand(2, 3, h, w),)
        names, outputs = ["image"], ["depth"]
        dynamic = {"image": {0: batch}}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with torch.no_grad(), _quiet_exporter():
            program = torch.onnx.export(graph, example, dynamo=True, opset_version=OPSET, input_names=names,
                                        output_names=outputs, dynamic_shapes=dynamic, verbose=False)
        model = program.model_proto
        del model.metadata_props[:]
        for key, value in metadata.items():
            model.metadata_props.add(key=key, value=value)
        onnx.save(model, str(tmp))
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def exported_model(spec: ExportSpec, load_net: Callable[[], nn.Module], cache_dir: str | Path | None = None,
                   setting: str = "runtime.cache_dir") -> Path:
    """The ONNX export of ``spec`` in ``cache_dir``, exported first when missing or stale.

    Args:
        spec: what to export. load_net: gives the loaded network (called only when an export is needed).
        cache_dir: the folder of exports (None: :func:`default_cache_dir`). setting: its config key, for messages.

    Raises:
        OSError: the cache folder cannot be written (one line naming ``setting``).
    """
    folder = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    expected = spec.metadata()
    path = folder / spec.file_name()
    if path.is_file():
        try:
            found = read_metadata(path)
        except Exception as err:  # a truncated or foreign file: export again
            found = {"unreadable": f"{type(err).__name__}: {err}"}
        stale = stale_fields(found, expected)
        if not stale:
            return path
        log.warning("%s: stale export (%s differ from %s); exporting it again", path,
                    ", ".join(stale), spec.checkpoint)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK):
            raise PermissionError(f"{folder} is not writable")
    except OSError as err:
        raise OSError(f"{setting}={folder}: cannot write the exported {spec.network} network there ({err}); set "
                      f"{setting}=DIR to a writable folder") from err
    log.info("exporting the %s network %s to %s", spec.network, spec.checkpoint, path)
    return export_onnx(load_net(), spec, path, expected)
