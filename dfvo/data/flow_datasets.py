"""Optical-flow datasets in their own layouts: FlyingChairs, FlyingThings3D, MPI-Sintel, KITTI flow 2012/2015.

Layouts (``root`` as named; a wrong layout raises an error naming the folder and what was expected)::

    FlyingChairs_release/data/NNNNN_img1.ppm, NNNNN_img2.ppm, NNNNN_flow.flo
    FlyingChairs_release/FlyingChairs_train_val.txt        line k (pair k): 1 = train, 2 = val
    FlyingThings3D/frames_cleanpass|frames_finalpass/TRAIN|TEST/A|B|C/NNNN/left|right/FFFF.png
    FlyingThings3D/optical_flow/TRAIN|TEST/A|B|C/NNNN/into_future|into_past/left|right/
        OpticalFlowIntoFuture_FFFF_L.pfm, OpticalFlowIntoPast_FFFF_L.pfm   (_R for the right camera)
    MPI-Sintel/training/clean|final/SCENE/frame_NNNN.png,  MPI-Sintel/training/flow/SCENE/frame_NNNN.flo
    KITTI 2012: training/colored_0/NNNNNN_10.png, NNNNNN_11.png, training/flow_occ|flow_noc/NNNNNN_10.png
    KITTI 2015: training/image_2/NNNNNN_10.png, NNNNNN_11.png, training/flow_occ|flow_noc/NNNNNN_10.png

Samples use the keys of :mod:`dfvo.data` that :class:`~dfvo.synthetic.SyntheticFlowDataset` gives and the
supervised flow module consumes: ``image``, ``image_next`` (3,H,W) float [0,1]; ``flow_fwd`` (2,H,W) flow
image→image_next on image's pixels, ``flow_fwd_valid`` (1,H,W) bool; ``flow_bwd`` / ``flow_bwd_valid`` the flow
image_next→image on image_next's pixels where the dataset has it (FlyingThings3D), else zeros with an all-False
mask (FlyingChairs, Sintel, KITTI: a loss over valid pixels then ignores it); ``index`` (). No ``K`` or
``dynamic_mask`` (these datasets have none). Validity is "the file defines the flow there": all pixels for the
dense synthetic sets, the LiDAR-covered pixels for KITTI.

Working size: ``resize=[h, w]`` first resizes images (bilinear) and flows (vectors scaled by the size ratios;
sparse flows are moved pixel by pixel so invalid pixels never blend in), then ``height``/``width`` crop both
images and flows with one window (``crop="center"`` or ``"random"``, drawn from torch's global generator).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Dataset

from dfvo.data.flow_io import read_flow
from dfvo.data.image_io import DatasetError, read_image, require_dir
from dfvo.data.transforms import resize_image
from dfvo.geometry.camera import resize_flow as resize_dense_flow

__all__ = ["FlowPair", "FlowPairDataset", "FlyingChairs", "FlyingThings3D", "Sintel", "KittiFlow", "resize_flow",
           "FLOW_DATASETS", "build_flow_dataset"]

CROPS = ("center", "random")


@dataclass
class FlowPair:
    """Files of one frame pair: ``image1`` → ``image2`` flow ``flow_fwd`` (and ``flow_bwd`` image2 → image1)."""

    image1: Path
    image2: Path
    flow_fwd: Path
    flow_bwd: Path | None = None
    name: str = ""
    extra: dict[str, Path] = field(default_factory=dict)


def resize_flow(flow: torch.Tensor, valid: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Resize a flow (2,H,W) with validity (1,H,W) to ``size`` = (h, w), vectors scaled by ``w/W``, ``h/H``.

    Fully valid flows are resized by :func:`dfvo.geometry.camera.resize_flow` (bilinear); sparse ones pixel by
    pixel: each valid pixel goes to the nearest target pixel (``x' = (x + 0.5) w/W - 0.5``), the flows landing on
    one target are averaged, and only targets that received one are valid.
    """
    H, W = flow.shape[-2:]
    h, w = int(size[0]), int(size[1])
    if (h, w) == (H, W):
        return flow, valid
    if bool(valid.all()):
        return resize_dense_flow(flow[None], (h, w))[0], torch.ones(1, h, w, dtype=torch.bool)
    scale = torch.tensor([w / W, h / H], dtype=flow.dtype).view(2, 1, 1)
    ys, xs = torch.nonzero(valid[0], as_tuple=True)
    xt = torch.round((xs.double() + 0.5) * w / W - 0.5).long()
    yt = torch.round((ys.double() + 0.5) * h / H - 0.5).long()
    keep = (xt >= 0) & (xt < w) & (yt >= 0) & (yt < h)
    target = yt[keep] * w + xt[keep]
    sums = torch.zeros(2, h * w, dtype=torch.float64).index_add_(1, target, flow[:, ys[keep], xs[keep]].double())
    count = torch.zeros(h * w, dtype=torch.float64).index_add_(0, target, torch.ones_like(target, dtype=torch.float64))
    out = (sums / count.clamp(min=1)).view(2, h, w).to(flow.dtype) * scale
    return out, (count > 0).view(1, h, w)


class FlowPairDataset(Dataset):
    """Frame pairs with true flow, read from files and brought to a working size.

    Args:
        pairs: the pairs' files.
        what: dataset name for error messages.
        height, width: crop size (None, None: no crop).
        resize: optional (h, w) to resize to before cropping.
        crop: ``"center"`` or ``"random"``.
    """

    def __init__(self, pairs: list[FlowPair], what: str, height: int | None = None, width: int | None = None,
                 resize: Any = None, crop: str = "center") -> None:
        if not pairs:
            raise DatasetError(f"{what}: no frame pairs found")
        if crop not in CROPS:
            raise ValueError(f"{what}: crop={crop!r}; expected one of {CROPS}")
        if (height is None) != (width is None) or (height is not None and (int(height) <= 0 or int(width) <= 0)):
            raise ValueError(f"{what}: height and width must both be positive or both null, got {height}, {width}")
        self.pairs, self.what, self.crop = pairs, what, crop
        self.size = None if height is None else (int(height), int(width))
        self.resize = None if resize is None else (int(resize[0]), int(resize[1]))

    def __len__(self) -> int:
        return len(self.pairs)

    def _read_flow(self, path: Path, hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        flow, valid = read_flow(path)
        if tuple(flow.shape[-2:]) != hw:
            raise DatasetError(f"{self.what}: flow {path} is {flow.shape[1]}x{flow.shape[2]}, its image is "
                               f"{hw[0]}x{hw[1]}")
        return flow, valid

    def load(self, i: int) -> dict[str, torch.Tensor]:
        """Sample ``i`` at the files' own resolution (no resize, no crop)."""
        p = self.pairs[i]
        img1 = read_image(p.image1)
        hw = tuple(img1.shape[-2:])
        img2 = read_image(p.image2, expected_size=hw)
        fwd, fwd_valid = self._read_flow(p.flow_fwd, hw)
        if p.flow_bwd is not None:
            bwd, bwd_valid = self._read_flow(p.flow_bwd, hw)
        else:
            bwd, bwd_valid = torch.zeros_like(fwd), torch.zeros_like(fwd_valid)
        return {"image": img1, "image_next": img2, "flow_fwd": fwd, "flow_fwd_valid": fwd_valid, "flow_bwd": bwd,
                "flow_bwd_valid": bwd_valid, "index": torch.tensor(i)}

    def _window(self, hw: tuple[int, int]) -> tuple[int, int]:
        (H, W), (h, w) = hw, self.size
        if h > H or w > W:
            raise ValueError(f"{self.what}: crop height x width = {h}x{w} does not fit the "
                             f"{'resized' if self.resize else 'native'} images of {H}x{W} (set a smaller "
                             "data.height/data.width or data.resize)")
        if self.crop == "center":
            return (H - h) // 2, (W - w) // 2
        return int(torch.randint(0, H - h + 1, ())), int(torch.randint(0, W - w + 1, ()))

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        s = self.load(i)
        if self.resize is not None:
            for key in ("image", "image_next"):
                s[key] = resize_image(s[key], *self.resize)
            for key in ("flow_fwd", "flow_bwd"):
                s[key], s[f"{key}_valid"] = resize_flow(s[key], s[f"{key}_valid"], self.resize)
        if self.size is not None:
            top, left = self._window(tuple(s["image"].shape[-2:]))
            h, w = self.size
            for key in ("image", "image_next", "flow_fwd", "flow_fwd_valid", "flow_bwd", "flow_bwd_valid"):
                s[key] = s[key][:, top:top + h, left:left + w].contiguous()
        return s


def _require_files(folder: Path, pattern: str, what: str, expected: str) -> list[Path]:
    folder = require_dir(folder, what)
    files = sorted(folder.glob(pattern))
    if not files:
        raise DatasetError(f"{what}: folder {folder} has no {pattern} files (expected {expected})")
    return files


def _size_kwargs(kwargs: dict[str, Any]) -> dict[str, Any]:
    return {k: kwargs[k] for k in ("height", "width", "resize", "crop") if k in kwargs}


class FlyingChairs(FlowPairDataset):
    """FlyingChairs (Dosovitskiy et al. 2015): ``root`` = ``FlyingChairs_release`` (or its ``data`` folder).

    Args:
        root: dataset folder.
        split: ``"train"`` (lines = 1 of ``FlyingChairs_train_val.txt``), ``"val"`` (= 2) or ``"all"``.
        **size: ``height``, ``width``, ``resize``, ``crop`` of :class:`FlowPairDataset`.
    """

    def __init__(self, root: str | Path, split: str = "train", **size: Any) -> None:
        root = require_dir(root, "FlyingChairs root")
        data = root / "data" if (root / "data").is_dir() else root
        what = "FlyingChairs"
        expected = "FlyingChairs_release/data/NNNNN_img1.ppm, NNNNN_img2.ppm, NNNNN_flow.flo"
        pairs = []
        for img1 in _require_files(data, "*_img1.ppm", what, expected):
            stem = img1.name[: -len("_img1.ppm")]
            img2, flo = data / f"{stem}_img2.ppm", data / f"{stem}_flow.flo"
            for f in (img2, flo):
                if not f.is_file():
                    raise DatasetError(f"{what}: {img1} has no partner {f.name} in {data} (expected {expected})")
            pairs.append(FlowPair(img1, img2, flo, name=stem))
        if split != "all":
            pairs = self._split(pairs, root, data, split)
        super().__init__(pairs, f"{what}({root}, split={split})", **_size_kwargs(size))

    @staticmethod
    def _split(pairs: list[FlowPair], root: Path, data: Path, split: str) -> list[FlowPair]:
        codes = {"train": 1, "val": 2}
        if split not in codes:
            raise ValueError(f"FlyingChairs: split={split!r}; expected 'train', 'val' or 'all'")
        candidates = [root / "FlyingChairs_train_val.txt", data.parent / "FlyingChairs_train_val.txt"]
        split_file = next((c for c in candidates if c.is_file()), None)
        if split_file is None:
            raise DatasetError(f"FlyingChairs: split={split} needs {candidates[0]} (one line per pair: 1 = train, "
                               "2 = val), or use split=all")
        lines = [int(t) for t in split_file.read_text().split()]
        chosen = []
        for p in pairs:
            k = int(p.name) if p.name.isdigit() else -1
            if not 1 <= k <= len(lines):
                raise DatasetError(f"FlyingChairs: pair {p.name} has no line in {split_file} ({len(lines)} lines)")
            if lines[k - 1] == codes[split]:
                chosen.append(p)
        return chosen


class FlyingThings3D(FlowPairDataset):
    """FlyingThings3D (Mayer et al. 2016) frame pairs (t, t+1) with into-future and into-past flow.

    Args:
        root: folder holding ``frames_cleanpass`` / ``frames_finalpass`` and ``optical_flow``.
        split: ``"train"`` (TRAIN) or ``"test"`` (TEST).
        dstype: ``"clean"`` or ``"final"`` pass.
        cameras: ``("left",)``, ``("right",)`` or both.
        reverse: also yield the reversed pairs (t+1, t) (forward flow = into-past of t+1).
        **size: ``height``, ``width``, ``resize``, ``crop`` of :class:`FlowPairDataset`.
    """

    def __init__(self, root: str | Path, split: str = "train", dstype: str = "clean",
                 cameras: tuple[str, ...] | list[str] = ("left",), reverse: bool = False, **size: Any) -> None:
        root = require_dir(root, "FlyingThings3D root")
        if split not in ("train", "test") or dstype not in ("clean", "final"):
            raise ValueError(f"FlyingThings3D: split={split!r}, dstype={dstype!r}; expected train|test, clean|final")
        part = split.upper()
        frames_root = require_dir(root / f"frames_{dstype}pass" / part, "FlyingThings3D frames")
        flow_root = require_dir(root / "optical_flow" / part, "FlyingThings3D optical_flow")
        pairs = []
        for cam in cameras:
            if cam not in ("left", "right"):
                raise ValueError(f"FlyingThings3D: camera {cam!r}; expected left or right")
            c = cam[0].upper()
            for scene in sorted(p for p in frames_root.glob(f"*/*/{cam}") if p.is_dir()):
                rel = scene.parent.relative_to(frames_root)
                frames = {int(f.stem): f for f in scene.glob("*.png") if f.stem.isdigit()}
                fdir = flow_root / rel / "into_future" / cam
                pdir = flow_root / rel / "into_past" / cam
                for k in sorted(frames):
                    fut = fdir / f"OpticalFlowIntoFuture_{k:04d}_{c}.pfm"
                    past = pdir / f"OpticalFlowIntoPast_{k + 1:04d}_{c}.pfm"
                    if k + 1 not in frames or not fut.is_file():
                        continue
                    bwd = past if past.is_file() else None
                    pairs.append(FlowPair(frames[k], frames[k + 1], fut, bwd, name=f"{rel}/{cam}/{k:04d}"))
                    if reverse and bwd is not None:
                        pairs.append(FlowPair(frames[k + 1], frames[k], past, fut, name=f"{rel}/{cam}/{k + 1:04d}r"))
        if not pairs:
            raise DatasetError(f"FlyingThings3D: no frame pair with flow under {frames_root} and {flow_root} "
                               "(expected A|B|C/NNNN/left/FFFF.png and into_future/left/OpticalFlowIntoFuture_"
                               "FFFF_L.pfm)")
        super().__init__(pairs, f"FlyingThings3D({root}, {split}, {dstype})", **_size_kwargs(size))


class Sintel(FlowPairDataset):
    """MPI-Sintel training pairs (Butler et al. 2012): ``training/<dstype>/SCENE/frame_NNNN.png`` with
    ``training/flow/SCENE/frame_NNNN.flo`` (flow NNNN → NNNN+1).

    Args:
        root: the ``MPI-Sintel-complete`` folder (or its ``training`` folder).
        dstype: ``"clean"`` or ``"final"`` pass.
        scenes: scene names to keep (None: all).
        **size: ``height``, ``width``, ``resize``, ``crop`` of :class:`FlowPairDataset`.
    """

    def __init__(self, root: str | Path, dstype: str = "clean", scenes: list[str] | None = None,
                 **size: Any) -> None:
        root = require_dir(root, "MPI-Sintel root")
        train = root / "training" if (root / "training").is_dir() else root
        if dstype not in ("clean", "final"):
            raise ValueError(f"Sintel: dstype={dstype!r}; expected clean or final")
        img_root = require_dir(train / dstype, f"MPI-Sintel {dstype} pass")
        flow_root = require_dir(train / "flow", "MPI-Sintel flow")
        pairs = []
        for flo in _require_files(flow_root, "*/frame_*.flo", "MPI-Sintel flow",
                                  "training/flow/SCENE/frame_NNNN.flo"):
            scene = flo.parent.name
            if scenes is not None and scene not in scenes:
                continue
            k = int(re.sub(r"\D", "", flo.stem))
            img1, img2 = img_root / scene / f"frame_{k:04d}.png", img_root / scene / f"frame_{k + 1:04d}.png"
            if not (img1.is_file() and img2.is_file()):
                raise DatasetError(f"MPI-Sintel: flow {flo} has no frames {img1.name}, {img2.name} in "
                                   f"{img_root / scene}")
            pairs.append(FlowPair(img1, img2, flo, name=f"{scene}/{k:04d}"))
        super().__init__(pairs, f"Sintel({root}, {dstype})", **_size_kwargs(size))


class KittiFlow(FlowPairDataset):
    """KITTI flow 2012 / 2015 training pairs: ``NNNNNN_10.png`` → ``NNNNNN_11.png`` with sparse true flow.

    Args:
        root: the ``training`` folder (or the folder holding it).
        version: 2012 (images ``colored_0``) or 2015 (``image_2``).
        mask: ``"occ"`` (all pixels with ground truth, ``flow_occ``) or ``"noc"`` (non-occluded, ``flow_noc``).
        images: require the frames (False: the ground truth alone, for scoring precomputed flows; the pairs'
            image paths may then not exist).
        **size: ``height``, ``width``, ``resize``, ``crop`` of :class:`FlowPairDataset`.

    Each pair's ``extra`` holds the ``flow_occ`` and ``flow_noc`` files that exist (for evaluation).
    """

    def __init__(self, root: str | Path, version: int = 2015, mask: str = "occ", images: bool = True,
                 **size: Any) -> None:
        root = require_dir(root, f"KITTI {version} flow root")
        train = root / "training" if (root / "training").is_dir() else root
        image_dir = {2012: "colored_0", 2015: "image_2"}.get(int(version))
        if image_dir is None or mask not in ("occ", "noc"):
            raise ValueError(f"KittiFlow: version={version}, mask={mask!r}; expected 2012|2015 and occ|noc")
        image_folder = train / image_dir
        if images:
            require_dir(image_folder, f"KITTI {version} flow images")
        expected = f"training/{image_dir}/NNNNNN_10.png, NNNNNN_11.png and training/flow_{mask}/NNNNNN_10.png"
        pairs = []
        for gt in _require_files(train / f"flow_{mask}", "*_10.png", f"KITTI {version} flow_{mask}", expected):
            name = gt.name[: -len("_10.png")]
            img1, img2 = image_folder / f"{name}_10.png", image_folder / f"{name}_11.png"
            if images and not (img1.is_file() and img2.is_file()):
                raise DatasetError(f"KITTI {version}: ground truth {gt} has no frames {img1.name}, {img2.name} in "
                                   f"{image_folder} (expected {expected})")
            extra = {m: train / f"flow_{m}" / gt.name for m in ("occ", "noc")
                     if (train / f"flow_{m}" / gt.name).is_file()}
            pairs.append(FlowPair(img1, img2, gt, name=name, extra=extra))
        self.version = int(version)
        super().__init__(pairs, f"KITTI {version} flow ({train}, {mask})", **_size_kwargs(size))


def _flyingchairs(root: Any, c: Callable[[str, Any], Any], split: str, size: dict) -> FlowPairDataset:
    return FlyingChairs(root, split=split, **size)


def _flyingthings(root: Any, c: Callable[[str, Any], Any], split: str, size: dict) -> FlowPairDataset:
    return FlyingThings3D(root, split=split, dstype=c("dstype", "clean"), cameras=tuple(c("cameras", ["left"])),
                          reverse=bool(c("reverse", False)), **size)


def _sintel(root: Any, c: Callable[[str, Any], Any], split: str, size: dict) -> FlowPairDataset:
    scenes = c("val_scenes" if split == "val" else "scenes", None)
    return Sintel(root, dstype=c("dstype", "clean"), scenes=list(scenes) if scenes else None, **size)


def _kitti_flow(root: Any, c: Callable[[str, Any], Any], split: str, size: dict) -> FlowPairDataset:
    return KittiFlow(root, version=int(c("version", 2015)), mask=c("mask", "occ"), **size)


FLOW_DATASETS: dict[str, Callable[..., FlowPairDataset]] = {
    "flyingchairs": _flyingchairs, "flyingthings": _flyingthings, "sintel": _sintel, "kitti_flow": _kitti_flow}


def build_flow_dataset(name: str, get: Callable[[str, Any], Any], split: str, train: bool) -> FlowPairDataset:
    """The flow dataset ``name`` (a key of :data:`FLOW_DATASETS`) from config values.

    Args:
        name: dataset kind (``data.kind``).
        get: ``get(key, default)`` reading ``data.<key>`` (root, height, width, resize, crop, and the dataset's
            own keys: dstype, cameras, reverse, scenes / val_scenes, version, mask).
        split: the dataset's split to read (``train`` / ``val`` / ``test`` / ``all``).
        train: training set (random crop when ``data.crop`` says so) or validation set (always centre crop).
    """
    if name not in FLOW_DATASETS:
        raise ValueError(f"data.kind={name!r}; expected one of {sorted(FLOW_DATASETS)}")
    root = get("root", None)
    if not root:
        raise ValueError(f"data={name}: set data.root= to the dataset folder")
    resize = get("resize", None)
    size = {"height": get("height", None), "width": get("width", None),
            "resize": list(resize) if resize else None, "crop": get("crop", "center") if train else "center"}
    try:
        return FLOW_DATASETS[name](root, get, split, size)
    except (OSError, ValueError) as err:
        raise type(err)(f"data={name} (data.root={root}): {err}") from err
