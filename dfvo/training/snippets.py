"""Temporal snippets with frame skips from any frame dataset: (i-s, i, i+s) for every gap s of a list.

Convention:
    A snippet is the target frame's sample (keys of :mod:`dfvo.data`: ``image`` (3,H,W), ``K`` (3,3), ``index``,
    and ``pose`` (4,4) ``T_w_c``, ``image_right``, ``T_right_left`` when the frame dataset gives them) plus
    ``image_prev`` = image of frame i-s, ``image_next`` = image of frame i+s (3,H,W), ``pose_prev`` / ``pose_next``
    (4,4) when the neighbours have a ``pose``, and ``frame_skip`` () = s. Frames i-s and i+s belong to the same
    sequence (drive) as i; targets are the frames with both neighbours inside it. The items are ordered by
    sequence, then gap, then target frame (with ``frame_skips=[1]``: the order of the datasets' own snippets).

A flow model reads a snippet as the pairs (i-s → i) and (i → i+s); a depth-pose model as the target with two
source views s frames away.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.utils.data import Dataset

__all__ = ["SkipSnippets"]


class SkipSnippets(Dataset):
    """Snippets (i-s, i, i+s), s in ``frame_skips``, of the frames of ``frames``.

    Args:
        frames: a frame dataset (each item one frame's sample).
        sequences: the dataset indices of each sequence, in temporal order (e.g. ``[range(len(frames))]`` for one
            sequence); neighbours are taken within a sequence only.
        frame_skips: the gaps s (each >= 1).
        neighbours: the dataset the neighbour frames are read from (same indexing as ``frames``; e.g. a left-camera
            only copy of a stereo dataset, so neighbours do not load the right images). None: ``frames``.

    Raises:
        ValueError: an empty or non-positive ``frame_skips``, a neighbour dataset of another length, or no snippet
            (every sequence shorter than ``2 * s + 1`` frames for every s).
    """

    def __init__(self, frames: Dataset, sequences: Sequence[Sequence[int]], frame_skips: Sequence[int] = (1,),
                 neighbours: Dataset | None = None) -> None:
        skips = [int(s) for s in frame_skips]
        if not skips or min(skips) < 1:
            raise ValueError(f"SkipSnippets: frame_skips={list(frame_skips)}; expected gaps >= 1")
        self.frames = frames
        self.neighbours = neighbours if neighbours is not None else frames
        if len(self.neighbours) != len(frames):
            raise ValueError(f"SkipSnippets: the neighbour dataset has {len(self.neighbours)} frames, the frame "
                             f"dataset {len(frames)}; expected the same frames")
        self.frame_skips = tuple(skips)
        self.items: list[tuple[int, int, int, int]] = []  # (prev, target, next, skip) dataset indices
        for seq in sequences:
            seq = list(seq)
            for s in skips:
                self.items += [(seq[p - s], seq[p], seq[p + s], s) for p in range(s, len(seq) - s)]
        if not self.items:
            lengths = [len(list(seq)) for seq in sequences]
            raise ValueError(f"SkipSnippets: no snippet: sequences of {lengths} frames, frame_skips={skips} need "
                             f"at least 2*s+1 frames")

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        prev_i, target_i, next_i, skip = self.items[i]
        sample = dict(self.frames[target_i])
        sample.pop("timestamp", None)  # float64 seconds; not a training input
        prev, nxt = self.neighbours[prev_i], self.neighbours[next_i]
        sample["image_prev"], sample["image_next"] = prev["image"], nxt["image"]
        if "pose" in sample and "pose" in prev and "pose" in nxt:
            sample["pose_prev"], sample["pose_next"] = prev["pose"], nxt["pose"]
        sample["frame_skip"] = torch.tensor(skip)
        return sample
