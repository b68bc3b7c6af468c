"""Training samples of the phantom CNN (the paper's Sec. III-A/B): labelled pillars, each with the
24 x 24 x 30 voxel window of point counts the network reads (its 11 x 11 pillar neighbourhood plus
one voxel of context, see network.py).

The paper annotated pillars by hand; we take the pillar labels from per-point reference labels
(simulator ground truth, SemanticKITTI labels) with the rule of `evaluation/reference.py`. Before
the ground estimate and the voxelisation the whole cloud is rotated about the vertical axis
through its centroid by a random angle ("we have rotated the input point cloud segments around
the vertical (z) axis with randomly selected angles"), so street directions do not become a
feature.

Storage: a float32 window is 24 * 24 * 30 * 4 B = 69 KB, 40,000 of them 2.8 GB. Windows are kept
as uint8 point counts clipped at 255 (17 KB each, 0.7 GB for 40,000) and turned into float32 per
batch (`Samples.batch`). More than 255 points in one 0.1 m voxel only happens right next to the
scanner or where the vehicle stood still; the network reads log1p(counts), so the clip changes such
a voxel's input from >= 5.55 to 5.55.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch

from app.core.labels import PillarClass
from app.io.accumulate import accumulate
from app.io.survey import Survey
from app.pipelines.phantom.classify import band_tensor, window_tensor
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.evaluation.reference import reference_pillar_labels, static_and_moving
from app.pipelines.phantom.network import CLASS_NAMES, CONTEXT_BANDS, CONTEXT_SPAN, COUNT_CLIP
from app.pipelines.phantom.pillars import PillarMap, build_pillar_map, phantom_ground

N_CLASSES = len(CLASS_NAMES)
TILE_PILLARS = 32  # windows are cut tile by tile so each dense block stays small


@dataclass
class LabelledMap:
    """An accumulated map with per-point reference labels (static class id + moving flag)."""

    xyz: np.ndarray  # (N, 3) float64 world coordinates
    semantic: np.ndarray  # (N,) int SemanticKITTI id, static meaning
    moving: np.ndarray  # (N,) bool
    source: str
    passes: np.ndarray | None = None  # (N,) int64 scanner pass (the frame) of each point

    def __len__(self) -> int:
        return len(self.xyz)


def labelled_map_from_survey(survey: Survey) -> LabelledMap:
    """Every frame's world points and reference labels, accumulated (sim, semantickitti)."""
    if not len(survey.frames):
        raise ValueError(f"survey {survey.name} has no frames")
    amap = accumulate(survey, with_reference=True, with_passes=True)
    if "semantic" not in amap.reference:
        raise ValueError(f"survey {survey.name}: its frames have no semantic reference labels")
    semantic, moving = static_and_moving(amap.reference)
    return LabelledMap(
        xyz=amap.xyz,
        semantic=semantic,
        moving=moving,
        source=survey.name,
        passes=None if survey.is_map else amap.passes,
    )


def frame_windows(lmap: LabelledMap, frames: int) -> list[LabelledMap]:
    """The map cut into consecutive windows of `frames` scanner passes (frames), each one map:
    a long simulated rotating-scanner drive gives maps like the 10-frame real ones."""
    if lmap.passes is None:
        raise ValueError(f"{lmap.source}: a map without frames cannot be cut into frame windows")
    window = lmap.passes // frames
    order = np.argsort(window, kind="stable")  # frame order already, for a drive
    parts = np.split(order, np.flatnonzero(np.diff(window[order])) + 1)
    return [
        LabelledMap(
            xyz=lmap.xyz[part],
            semantic=lmap.semantic[part],
            moving=lmap.moving[part],
            source=f"{lmap.source}:frames{int(window[part[0]]) * frames}",
            passes=lmap.passes[part],
        )
        for part in parts
        if len(part)
    ]


@dataclass
class Samples:
    """Labelled pillars with their input windows.

    `x` (S, C, 30, 24, 24) uint8 point counts (and passes, C = 2) clipped at 255 (module
    docstring), `y` (S,) int64 class index into CLASS_NAMES, `source` (S,) the map each sample
    came from, `xy` (S, 2) the pillar centre in the map's own (unrotated) frame, so rotated
    copies of a pillar share it (spatially blocked k-fold splits, train.py), `group` (S,) int64
    an id of the underlying sample (copies drawn by `balanced` share it), `sources` one
    JSON-ready dict per map (points, pillars per class, samples taken).
    """

    x: np.ndarray
    y: np.ndarray
    source: np.ndarray
    xy: np.ndarray | None = None
    group: np.ndarray | None = None
    sources: list[dict] = field(default_factory=list)
    bands: np.ndarray | None = None  # (S, 6, 31, 31) uint8 context-branch input, when built

    def __post_init__(self) -> None:
        self.y = np.asarray(self.y, dtype=np.int64)
        self.source = np.asarray(self.source, dtype=str)
        if self.xy is None:
            self.xy = np.zeros((len(self.y), 2))
        if self.group is None:
            self.group = np.arange(len(self.y), dtype=np.int64)
        sizes = {len(self.x), len(self.y), len(self.source), len(self.xy), len(self.group)}
        if self.bands is not None:
            sizes.add(len(self.bands))
        if len(sizes) != 1:
            raise ValueError(
                f"Samples: {len(self.x)} windows, {len(self.y)} labels, {len(self.source)} "
                f"sources, {len(self.xy)} locations, {len(self.group)} groups"
            )

    def __len__(self) -> int:
        return len(self.y)

    def class_counts(self) -> dict[str, int]:
        counts = np.bincount(self.y, minlength=N_CLASSES)
        return {name: int(counts[i]) for i, name in enumerate(CLASS_NAMES)}

    def subset(self, index: np.ndarray) -> Samples:
        index = np.asarray(index, dtype=np.int64)
        return Samples(
            self.x[index],
            self.y[index],
            self.source[index],
            self.xy[index],
            self.group[index],
            list(self.sources),
            None if self.bands is None else self.bands[index],
        )

    def batch(self, index: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(float32 windows (B, C, 30, 24, 24), int64 labels (B,)) of the given samples."""
        index = np.asarray(index, dtype=np.int64)
        x = torch.from_numpy(self.x[index]).to(torch.float32)
        return x, torch.from_numpy(self.y[index])

    def context_batch(self, index: np.ndarray) -> torch.Tensor | None:
        """float32 band counts (B, 6, 31, 31) of the given samples, None when not built."""
        if self.bands is None:
            return None
        return torch.from_numpy(self.bands[np.asarray(index, dtype=np.int64)]).to(torch.float32)


def concatenate(parts: list[Samples]) -> Samples:
    """One sample set from several; groups stay distinct between the parts."""
    if not parts:
        raise ValueError("no samples to concatenate")
    groups, offset = [], 0
    for part in parts:
        groups.append(part.group + offset)
        offset += int(part.group.max()) + 1 if len(part) else 0
    return Samples(
        x=np.concatenate([p.x for p in parts]),
        y=np.concatenate([p.y for p in parts]),
        source=np.concatenate([p.source for p in parts]),
        xy=np.concatenate([p.xy for p in parts]),
        group=np.concatenate(groups),
        sources=[s for p in parts for s in p.sources],
        bands=np.concatenate([p.bands for p in parts]) if parts[0].bands is not None else None,
    )


def rotate_about_z(xyz: np.ndarray, angle: float, centre: np.ndarray | None = None) -> np.ndarray:
    """The cloud rotated by `angle` (radians) about the vertical axis through `centre` (default:
    its centroid)."""
    centre = xyz.mean(axis=0) if centre is None else np.asarray(centre, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    out = xyz - centre
    x, y = out[:, 0].copy(), out[:, 1].copy()
    out[:, 0] = c * x - s * y
    out[:, 1] = s * x + c * y
    return out + centre


def labelled_pillars(
    lmap: LabelledMap, config: PhantomConfig, angle: float = 0.0, passes: bool = False
) -> tuple[PillarMap, np.ndarray]:
    """The pillar map of the (rotated) cloud and each occupied pillar's reference class; with
    `passes`, the map also counts distinct scanner passes per voxel."""
    if passes and lmap.passes is None:
        raise ValueError(f"{lmap.source}: no scanner passes (point times) for a passes network")
    xyz = rotate_about_z(lmap.xyz, angle) if angle else lmap.xyz
    ground = phantom_ground(xyz, config)
    pm = build_pillar_map(xyz, ground, config, lmap.passes if passes else None)
    return pm, reference_pillar_labels(pm, lmap.semantic, lmap.moving)


def window_counts(
    pm: PillarMap, pillars: np.ndarray, batch: int = 512, cut: Callable = window_tensor
) -> np.ndarray:
    """(S, C, 30, 24, 24) uint8 windows of the given pillars (`window_tensor`, clipped at 255;
    C = 2 when the pillar map has scanner passes), cut tile by tile (TILE_PILLARS) so each
    dense block covers only a small area; with `cut=band_tensor` the (S, 6, 31, 31) band counts
    of the context branch instead."""
    pillars = np.asarray(pillars, dtype=np.int64).reshape(-1, 2)
    out = None
    if cut is window_tensor and pm.passes is not None:
        cut = partial(window_tensor, passes=True)
    if not len(pillars):
        side = pm.config.window_voxels + 2
        shape = (pm.channels, pm.config.voxels_high, side, side)
        if cut is band_tensor:
            shape = (CONTEXT_BANDS, CONTEXT_SPAN, CONTEXT_SPAN)
        return np.empty((0, *shape), dtype=np.uint8)
    tiles = np.floor_divide(pillars, TILE_PILLARS)
    _, tile_id = np.unique(tiles, axis=0, return_inverse=True)
    order = np.argsort(tile_id.ravel(), kind="stable")
    bounds = np.flatnonzero(np.diff(tile_id.ravel()[order])) + 1
    for members in np.split(order, bounds):
        for a in range(0, len(members), batch):
            part = members[a : a + batch]
            windows = cut(pm, pillars[part]).numpy()
            if out is None:
                out = np.empty((len(pillars), *windows.shape[1:]), dtype=np.uint8)
            out[part] = np.minimum(windows, COUNT_CLIP).astype(np.uint8)
    return out


def _cap(max_per_class: int | dict[int, int] | None, cls: int) -> int | None:
    if isinstance(max_per_class, dict):
        return max_per_class.get(cls)
    return max_per_class


def pillar_samples(
    lmap: LabelledMap,
    config: PhantomConfig | None = None,
    rng: np.random.Generator | None = None,
    rotate: bool = True,
    max_per_class: int | dict[int, int] | None = None,
    batch: int = 512,
    context: bool = False,
    passes: bool = False,
) -> Samples:
    """Every labelled pillar of the map that the pipeline would give to the CNN
    (`PillarMap.candidates`: the rest is ground without asking it) as a sample, a random subset of
    at most `max_per_class` per class; a dict {class index: cap} caps classes one by one, 0 skips
    a class. Ground samples are thus the hard ones (curbs, low vegetation, the fringe of objects),
    topped up with random plain-road pillars where there are fewer of them than the cap (with no
    cap: than the largest other class).

    With `rotate` the cloud is first turned about z through its centroid by a uniform random angle.
    With `context` the samples also carry the context branch's band counts (network.py); with
    `passes` the windows carry the distinct scanner passes per voxel as a second channel.
    `sources[0]` records the map's point count and pillars per class (before capping).
    """
    config = config or PhantomConfig()
    rng = rng if rng is not None else np.random.default_rng()
    angle = float(rng.uniform(0.0, 2.0 * np.pi)) if rotate else 0.0
    pm, labels = labelled_pillars(lmap, config, angle, passes)
    judged = np.zeros(len(labels), dtype=bool)
    judged[pm.candidates()] = True
    chosen = []
    for cls in range(N_CLASSES):
        index = np.flatnonzero((labels == cls) & judged)
        cap = _cap(max_per_class, cls)
        if cap is not None and len(index) > cap:
            index = np.sort(rng.choice(index, size=cap, replace=False))
        chosen.append(index)
    # judged ground is rare on some maps (none on a flat road): top ground up with plain road
    want = _cap(max_per_class, PillarClass.ground)
    want = max(len(c) for c in chosen) if want is None else want
    plain = np.flatnonzero((labels == PillarClass.ground) & ~judged)
    extra = min(max(want - len(chosen[PillarClass.ground]), 0), len(plain))
    if extra:
        fill = rng.choice(plain, size=extra, replace=False)
        chosen[PillarClass.ground] = np.sort(np.r_[chosen[PillarClass.ground], fill])
    index = np.concatenate(chosen)
    y = labels[index].astype(np.int64)
    pillar_counts = np.bincount(labels, minlength=N_CLASSES)
    judged_counts = np.bincount(labels[judged], minlength=N_CLASSES)
    sample_counts = np.bincount(y, minlength=N_CLASSES)
    info = {
        "name": lmap.source,
        "points": int(len(lmap)),
        "rotation_deg": round(float(np.degrees(angle)), 3),
        "pillars": {name: int(pillar_counts[i]) for i, name in enumerate(CLASS_NAMES)},
        "judged_pillars": {name: int(judged_counts[i]) for i, name in enumerate(CLASS_NAMES)},
        "samples": {name: int(sample_counts[i]) for i, name in enumerate(CLASS_NAMES)},
    }
    # where each sample's pillar centre lies in the map before the rotation
    centres = np.zeros((len(index), 3))
    centres[:, :2] = (pm.pillars[index] + 0.5) * config.cell_size
    if angle:
        centres = rotate_about_z(centres, -angle, lmap.xyz.mean(axis=0))
    return Samples(
        x=window_counts(pm, pm.pillars[index], batch),
        bands=window_counts(pm, pm.pillars[index], batch, band_tensor) if context else None,
        y=y,
        source=np.full(len(index), lmap.source),
        xy=centres[:, :2],
        sources=[info],
    )


def balanced(
    samples: Samples, per_class: int, rng: np.random.Generator, allow_missing: bool = False
) -> Samples:
    """`per_class` samples of every class (the paper trained on 10,000 per class), shuffled.

    A class with at least `per_class` samples gives a random subset without replacement; a class
    with fewer gives each of its samples once and draws the rest with replacement (the copies keep
    their `group`, so k-fold splits never put a copy on both sides). A class with no samples at
    all is an error: the network could not learn it; with `allow_missing` (fine-tuning a trained
    network on the classes people labelled) it is left out.
    """
    if per_class < 1:
        raise ValueError(f"per_class must be at least 1, got {per_class}")
    picks = []
    for cls, name in enumerate(CLASS_NAMES):
        index = np.flatnonzero(samples.y == cls)
        if not len(index):
            if allow_missing:
                continue
            raise ValueError(f"no training samples of class {name!r}")
        if len(index) >= per_class:
            picks.append(rng.choice(index, size=per_class, replace=False))
        else:
            extra = rng.choice(index, size=per_class - len(index), replace=True)
            picks.append(np.concatenate([index, extra]))
    order = rng.permutation(np.concatenate(picks))
    return samples.subset(order)
