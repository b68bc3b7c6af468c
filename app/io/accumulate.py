"""Accumulation: a survey's frames posed into one map, with where each point came from.

Every reader of a whole survey at once (the phantom pipeline and its evaluation, clutter's cleaned
and removed maps, the viewer's map) builds it here, each frame read once. Points stay in frame
order and, inside a frame, in file order, so per-point results split back into per-frame arrays
(`split`), `source_frame` / `source_index` say where each point came from, and `select` keeps a
subset in that order (clutter's kept and removed points).

World coordinates stay float64. With an `origin`, the points are re-centred on it as float32
frame by frame (what a viewer sends; float32 of world coordinates loses centimetres), and
`world_xy` keeps the exact float64 world xy beside them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from app.core.errors import InputError
from app.io.survey import Frame, Survey


@dataclass
class AccumulatedMap:
    """Frames of a survey in the map frame, with where each point came from."""

    xyz: np.ndarray  # (N, 3) float64 world; float32 relative to the origin when one was given
    frame_ids: list[str]
    frame_sizes: list[int]  # points of each frame in this map
    reference: dict[str, np.ndarray] = field(default_factory=dict)  # per point, when present
    intensity: np.ndarray | None = None  # (N,) float32, when asked for and every frame has it
    world_xy: np.ndarray | None = None  # (N, 2) float64 world xy, beside re-centred xyz
    index: np.ndarray | None = None  # (N,) uint32 point of its frame; None: all, in file order
    passes: np.ndarray | None = None  # (N,) int64 scanner pass of each point (`scanner_passes`)

    def split(self, values: np.ndarray) -> dict[str, np.ndarray]:
        """Per-point values back into per-frame arrays (file order)."""
        parts = np.split(values, np.cumsum(self.frame_sizes)[:-1])
        return dict(zip(self.frame_ids, parts, strict=True))

    @property
    def source_frame(self) -> np.ndarray:
        """(N,) uint32 index of each point's frame."""
        return np.repeat(np.arange(len(self.frame_sizes), dtype=np.uint32), self.frame_sizes)

    @property
    def source_index(self) -> np.ndarray:
        """(N,) uint32 index of each point in its frame."""
        if self.index is not None:
            return self.index
        if not self.frame_sizes:
            return np.zeros(0, dtype=np.uint32)
        return np.concatenate([np.arange(n, dtype=np.uint32) for n in self.frame_sizes])

    def select(self, which: np.ndarray) -> AccumulatedMap:
        """The points `which` (a boolean mask, or ascending indices), in the same order."""
        frame = self.source_frame[which]
        return AccumulatedMap(
            xyz=self.xyz[which],
            frame_ids=self.frame_ids,
            frame_sizes=np.bincount(frame, minlength=len(self.frame_ids)).tolist(),
            reference={name: values[which] for name, values in self.reference.items()},
            intensity=None if self.intensity is None else self.intensity[which],
            world_xy=None if self.world_xy is None else self.world_xy[which],
            index=self.source_index[which],
            passes=None if self.passes is None else self.passes[which],
        )


def accumulate(
    survey: Survey,
    with_reference: bool = False,
    with_intensity: bool = False,
    origin: np.ndarray | None = None,
    with_passes: bool = False,
) -> AccumulatedMap:
    """Every frame's points posed into the map frame. `with_reference` keeps the survey's
    reference labels (when every frame has them), `with_intensity` the intensities as float32
    (when every frame has them), `origin` re-centres the points on it as float32,
    `with_passes` numbers the scanner pass of every point (`scanner_passes`; None when a map
    has no point times)."""
    if origin is not None:
        origin = np.asarray(origin, dtype=np.float64)
    clouds, refs, intensities, world_xy, times = [], [], [], [], []
    for frame in survey.frames:
        cloud = frame.world_points()
        xyz = cloud.xyz
        if with_passes and survey.is_map:
            times.append(cloud.time)
        if origin is not None:
            world_xy.append(xyz[:, :2].copy())  # a copy: the float64 frame is not kept alive
            xyz = (xyz - origin).astype(np.float32)
        clouds.append(xyz)
        if with_intensity:
            values = cloud.intensity
            intensities.append(None if values is None else np.asarray(values, np.float32))
        if with_reference and survey.reference_label_kinds:
            refs.append(_checked_reference(survey, frame, len(xyz)))
    if not clouds:
        local = origin is not None
        return AccumulatedMap(
            xyz=np.zeros((0, 3), dtype=np.float32 if local else np.float64),
            frame_ids=[],
            frame_sizes=[],
            world_xy=np.zeros((0, 2)) if local else None,
        )
    reference = {}
    if refs and all(refs):
        reference = {k: np.concatenate([r[k] for r in refs]) for k in refs[0]}
    with_values = with_intensity and all(v is not None for v in intensities)
    return AccumulatedMap(
        xyz=np.concatenate(clouds),
        frame_ids=[f.frame_id for f in survey.frames],
        frame_sizes=[len(c) for c in clouds],
        reference=reference,
        intensity=np.concatenate(intensities) if with_values else None,
        world_xy=np.concatenate(world_xy) if origin is not None else None,
        passes=scanner_passes(survey, [len(c) for c in clouds], times) if with_passes else None,
    )


def accumulate_window(
    survey: Survey,
    keep: Callable[[np.ndarray], np.ndarray],
    with_reference: bool = False,
    with_passes: bool = False,
    pass_t0: float | None = None,
) -> AccumulatedMap:
    """The points `keep(world xyz)` selects (a tile's window), read frame by frame and, from a
    map file, chunk by chunk (`Frame.world_chunks`): a window of a survey of any size without
    holding the rest. `index` says which point of its frame each one is. A map's scanner passes
    are binned from `pass_t0` (the survey's first time, so that every window bins alike)."""
    clouds, refs, times, indices, sizes = [], [], [], [], []
    kinds = survey.reference_label_kinds if with_reference else ()
    for frame in survey.frames:
        whole = None  # reference labels of a frame read whole, when its chunks lack them
        kept = 0
        for start, cloud in frame.world_chunks():
            mask = np.asarray(keep(cloud.xyz), dtype=bool)
            clouds.append(cloud.xyz[mask])
            indices.append((start + np.flatnonzero(mask)).astype(np.uint32))
            kept += int(mask.sum())
            if with_passes and survey.is_map:
                times.append(None if cloud.time is None else cloud.time[mask])
            if kinds:
                if all(k in cloud.extra for k in kinds):
                    refs.append({k: cloud.extra[k][mask] for k in kinds})
                else:
                    whole = whole or _checked_reference(survey, frame, start + len(cloud.xyz))
                    rows = start + np.flatnonzero(mask)
                    refs.append({k: v[rows] for k, v in whole.items()})
        sizes.append(kept)
    xyz = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    reference = {}
    if refs:
        reference = {k: np.concatenate([r[k] for r in refs]) for k in refs[0]}
    passes = None
    if with_passes:
        if survey.is_map:
            passes = _binned_passes(times, pass_t0)
        else:
            passes = np.repeat(np.arange(len(sizes), dtype=np.int64), sizes)
    return AccumulatedMap(
        xyz=xyz,
        frame_ids=[f.frame_id for f in survey.frames],
        frame_sizes=sizes,
        reference=reference,
        index=np.concatenate(indices) if indices else np.zeros(0, np.uint32),
        passes=passes,
    )


def _checked_reference(survey: Survey, frame: Frame, points: int) -> dict[str, np.ndarray]:
    """The frame's reference labels, one per point (a label file of another length is an
    error naming the frame, never a silently shifted label)."""
    reference = frame.reference_labels()
    for name, values in reference.items():
        if len(values) != points:
            raise InputError(
                frame.source_path or survey.source,
                f"frame {frame.frame_id} has {points} points and {len(values)} {name} labels",
            )
    return reference


PASS_SECONDS = 0.1  # a map's point times are binned into passes this long (one revolution)


def scanner_passes(
    survey: Survey, frame_sizes: list[int], map_times: list[np.ndarray | None]
) -> np.ndarray | None:
    """Which pass of the scanner measured each point: time as evidence (a static surface is
    measured again on every pass that sees it, a moving object at one place only once or twice).

    A survey of frames: the frame index (one revolution of a rotating scanner, one 0.1 s stretch
    of profiles). A map: its point times binned into `PASS_SECONDS`; None without point times
    (all zero counts as none: LAS writers fill missing GPS time with zeros).
    """
    if not survey.is_map:
        return np.repeat(np.arange(len(frame_sizes), dtype=np.int64), frame_sizes)
    return _binned_passes(map_times, None)


def _binned_passes(map_times: list[np.ndarray | None], t0: float | None) -> np.ndarray | None:
    """A map's point times binned into passes of `PASS_SECONDS` from t0 (default: the first
    time, when the times are usable: not all equal); None without usable times."""
    if not map_times or any(t is None for t in map_times):
        return None
    t = np.concatenate(map_times)
    if not np.all(np.isfinite(t)):
        return None
    if t0 is None:
        if not len(t) or np.ptp(t) == 0:
            return None
        t0 = float(t.min())
    return np.floor((t - t0) / PASS_SECONDS).astype(np.int64)
