"""Datasets over synthetic worlds (temporal snippets, frame pairs with exact flow, frame skips, scenario mixes),
and the held-out evaluation worlds (seeds >= ``HELD_OUT_SEED`` are never trained on)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch.utils.data import Dataset

from dfvo.synthetic.trajectory import SCENARIOS
from dfvo.synthetic.world import SyntheticWorld

__all__ = ["TRAINING_SPEED", "TRAINING_SCENARIOS", "HELD_OUT_SEED", "HELD_OUT_SPEED", "HeldOutWorld", "held_out_worlds",
           "check_training_seeds", "SyntheticSequenceDataset", "SyntheticFlowDataset"]

TRAINING_SPEED = (0.3, 3.0)  # m/frame: KITTI at 10 Hz spans ~3-30 m/s
TRAINING_SCENARIOS = ("drive", "city", "straight", "highway")
HELD_OUT_SEED = 1000  # seeds >= this are evaluation worlds, never trained on


@dataclass(frozen=True)
class HeldOutWorld:
    """An evaluation world: ``SyntheticWorld(seed=seed, scenario=scenario, speed=speed, ...)``, named ``name``."""

    name: str
    seed: int
    scenario: str
    speed: float | tuple[float, float] | None = None

    def make(self, num_frames: int = 100, height: int = 192, width: int = 640, **kwargs: Any) -> SyntheticWorld:
        """The world itself (further keyword arguments as :class:`SyntheticWorld`)."""
        return SyntheticWorld(seed=self.seed, num_frames=num_frames, height=height, width=width,
                              scenario=self.scenario, speed=self.speed, **kwargs)


# per scenario: the speed of its held-out worlds (None = the scenario's default)
HELD_OUT_SPEED: dict[str, float | tuple[float, float] | None] = {"drive": None, "city": None,
                                                                  "straight": TRAINING_SPEED, "highway": None}


def held_out_worlds(scenarios: Sequence[str] = TRAINING_SCENARIOS, per_scenario: int = 2) -> list[HeldOutWorld]:
    """Evaluation worlds, ``per_scenario`` of each scenario: seeds ``HELD_OUT_SEED + j`` (j = 0, 1, ...), speeds
    from ``HELD_OUT_SPEED`` (drive: the default ~1 m/frame residential worlds; city: 0.4-1.5 m/frame with
    corners; straight: a speed drawn in ``TRAINING_SPEED``; highway: 2-3 m/frame). Seeds >= ``HELD_OUT_SEED``
    are never used for training; benchmarks build each with ``HeldOutWorld.make(num_frames, height, width)``."""
    out = []
    for sc in scenarios:
        if sc not in SCENARIOS:
            raise ValueError(f"held_out_worlds: scenario={sc!r}; expected one of {SCENARIOS}")
        for j in range(per_scenario):
            out.append(HeldOutWorld(f"{sc}_s{HELD_OUT_SEED + j}", HELD_OUT_SEED + j, sc, HELD_OUT_SPEED.get(sc)))
    return out


def check_training_seeds(seeds: Sequence[int], setting: str = "data.seeds") -> None:
    """Raise (one line naming ``setting``) when a training seed is a held-out evaluation world (>= 1000)."""
    bad = [int(s) for s in seeds if int(s) >= HELD_OUT_SEED]
    if bad:
        raise ValueError(f"{setting}: seeds {bad} are held-out evaluation worlds (seeds >= {HELD_OUT_SEED} are never "
                         "trained on); use seeds below it")


class _WorldsDataset(Dataset):
    """Worlds of ``seeds`` and their items (world, frame, frame skip). ``scenario`` is one name or a sequence:
    the world of seed s gets ``scenario[s % len(scenario)]``; further keyword arguments go to each world."""

    def __init__(self, seeds: list[int], num_frames: int, height: int, width: int, frame_skips: Sequence[int] = (1,),
                 scenario: str | Sequence[str] = "drive", **world_kwargs: Any) -> None:
        name = type(self).__name__
        if not seeds:
            raise ValueError(f"{name}: seeds is empty; expected at least one world seed")
        skips = tuple(int(k) for k in frame_skips)
        if not skips or min(skips) < 1 or max(skips) > self._max_skip(num_frames):
            raise ValueError(f"{name}: frame_skips={tuple(frame_skips)}; expected skips >= 1 and <= "
                             f"{self._max_skip(num_frames)} for num_frames={num_frames}")
        names = [scenario] if isinstance(scenario, str) else list(scenario)
        if not names:
            raise ValueError(f"{name}: scenario is empty; expected a name or a sequence of names from {SCENARIOS}")
        self.frame_skips = skips
        self.worlds = [SyntheticWorld(seed=s, num_frames=num_frames, height=height, width=width,
                                      scenario=names[int(s) % len(names)], **world_kwargs) for s in seeds]
        self.items = [(w, k, skip) for w in range(len(seeds)) for skip in skips
                      for k in self._frames(num_frames, skip)]

    def _max_skip(self, n: int) -> int:
        raise NotImplementedError

    def _frames(self, n: int, skip: int) -> range:
        raise NotImplementedError

    def __len__(self) -> int:
        return len(self.items)


class SyntheticSequenceDataset(_WorldsDataset):
    """Temporal snippets with stereo and true depth, for depth-pose training (one per inner frame and skip).

    Args:
        seeds: one synthetic world per seed.
        num_frames, height, width: as :class:`SyntheticWorld`.
        frame_skips: snippet strides s; each item is frames (k-s, k, k+s) for every s (default (1,)).
        scenario: a scenario name, or a sequence of names (seed s gets ``scenario[s % len]``).
        keep_frames: keep every frame rendered (its images, depth and mask) for the dataset's life, so that each
            frame is rendered once instead of once per snippet and epoch (a frame is the previous, current and next
            image of three snippets). The items are the same tensors, bit for bit. Memory: about
            ``worlds x num_frames x 7 x H x W x 4`` bytes (24 worlds of 40 frames at 320x96: 0.8 GB), per
            DataLoader worker process.
        **world_kwargs: further :class:`SyntheticWorld` arguments (speed, turn_rate, device, noise_std, ...).

    Each item: ``image_prev``, ``image``, ``image_next``, ``image_right`` (3,H,W), ``K`` (3,3),
    ``T_right_left`` (4,4), ``pose``, ``pose_prev``, ``pose_next`` (4,4) ``T_w_c``, ``depth`` (1,H,W),
    ``dynamic_mask`` (1,H,W), ``index`` (), ``frame_skip`` () (s).
    """

    def __init__(self, seeds: list[int], num_frames: int, height: int, width: int, frame_skips: Sequence[int] = (1,),
                 scenario: str | Sequence[str] = "drive", keep_frames: bool = False, **world_kwargs: Any) -> None:
        super().__init__(seeds, num_frames, height, width, frame_skips, scenario, **world_kwargs)
        self.keep_frames = bool(keep_frames)
        self._kept: dict[tuple[int, int], dict[str, torch.Tensor]] = {}

    def _render(self, w: int, k: int) -> dict[str, torch.Tensor]:
        """Frame ``k`` of world ``w``: :meth:`SyntheticWorld.render` with the right image, without flow (kept when
        ``keep_frames``); a new dict each call (its tensors shared)."""
        out = self._kept.get((w, k))
        if out is None:
            out = self.worlds[w].render(k, right=True, flow=False)
            if self.keep_frames:
                self._kept[(w, k)] = out
        return dict(out)

    def _max_skip(self, n: int) -> int:
        return (n - 1) // 2

    def _frames(self, n: int, skip: int) -> range:
        return range(skip, n - skip)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        w, k, skip = self.items[i]
        world = self.worlds[w]
        out = self._render(w, k)
        poses = world.poses()
        if self.keep_frames:  # the neighbours' left images are their frames' own: rendered once, kept
            out["image_prev"] = self._render(w, k - skip)["image"]
            out["image_next"] = self._render(w, k + skip)["image"]
        else:
            out["image_prev"] = world.image(k - skip)
            out["image_next"] = world.image(k + skip)
        out["pose_prev"] = poses[k - skip].float().to(world.device)
        out["pose_next"] = poses[k + skip].float().to(world.device)
        out["frame_skip"] = torch.tensor(skip, device=world.device)
        return out


class SyntheticFlowDataset(_WorldsDataset):
    """Frame pairs (k, k+s) with exact forward/backward flow, for supervised and self-supervised flow training.

    Args:
        seeds: one synthetic world per seed.
        num_frames, height, width: as :class:`SyntheticWorld`.
        frame_skips: pair gaps s (e.g. (1, 2, 3)); every pair (k, k+s) of every world is an item (default (1,)).
        scenario: a scenario name, or a sequence of names (seed s gets ``scenario[s % len]``).
        **world_kwargs: further :class:`SyntheticWorld` arguments (speed, turn_rate, device, noise_std, ...).

    Each item: ``image`` (frame k), ``image_next`` (frame k+s) (3,H,W), ``flow_fwd`` (k->k+s on image k),
    ``flow_bwd`` (k+s->k on image k+s) (2,H,W), ``flow_fwd_valid``, ``flow_bwd_valid``, ``dynamic_mask`` (of
    image k) (1,H,W), ``K`` (3,3), ``index`` () (k), ``frame_skip`` () (s).
    """

    def _max_skip(self, n: int) -> int:
        return n - 1

    def _frames(self, n: int, skip: int) -> range:
        return range(0, n - skip)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        w, k, skip = self.items[i]
        world = self.worlds[w]
        out = world.render(k, right=False, flow=False)
        out["image_next"] = world.image(k + skip)
        out["flow_fwd"], out["flow_fwd_valid"] = world.flow(k, k + skip)
        out["flow_bwd"], out["flow_bwd_valid"] = world.flow(k + skip, k)
        out["frame_skip"] = torch.tensor(skip, device=world.device)
        for key in ("depth", "T_right_left", "pose"):
            out.pop(key)
        return out
