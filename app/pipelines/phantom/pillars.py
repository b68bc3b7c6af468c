"""Pillars and voxels (the paper's Sec. III-A): the map cut into s_c x s_c x 3 m columns that
stand on the local ground, each split into 2 x 2 x 30 voxels of 0.1 m holding point counts.

Indices are global and stable: voxel (vx, vy) = floor(x / 0.1), floor(y / 0.1); the pillar of a
voxel is (vx // 2, vy // 2). vz = floor(height above ground / 0.1) in [0, 30). Counts are kept
sparse (one entry per occupied voxel), so any map size fits; `dense_block` cuts out the dense
tensor of any window or tile.

Time as evidence (beyond the paper): with the scanner pass of every point (`scanner_passes` in
`app.io.accumulate`) a second channel counts, per voxel, the distinct passes that put a point in
it. A static surface is measured on every pass that sees it, a moving object at one place on one
or two passes; on SemanticKITTI this count alone ranks moving points above static ones with
AUROC 0.90-0.97 where the movers move. The network reads it beside the point counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry.ground import GroundModel, estimate_ground
from app.pipelines.phantom.config import PhantomConfig

_BIAS = 1 << 27  # voxel indices within +-2^27 (13,000 km at 0.1 m): UTM coordinates fit


@dataclass
class PillarMap:
    config: PhantomConfig
    vx: np.ndarray  # (M,) int64 occupied voxels, sorted by vx
    vy: np.ndarray  # (M,)
    vz: np.ndarray  # (M,)
    counts: np.ndarray  # (M,) float32 points per voxel
    pillars: np.ndarray  # (P, 2) int64 occupied pillars (ix, iy)
    point_pillar: np.ndarray  # (N,) int64 index into `pillars`, -1 outside the 3 m layer
    height: np.ndarray  # (N,) float64 height above the local ground
    object_points: np.ndarray  # (P,) int64 points of each pillar above `ground_tolerance`
    passes: np.ndarray | None = None  # (M,) float32 distinct scanner passes per voxel

    @property
    def in_layer(self) -> np.ndarray:
        return self.point_pillar >= 0

    def candidates(self) -> np.ndarray:
        """Indices of the pillars the CNN classifies: those with at least `min_object_points`
        points above ground level. The others are ground by the definition of the reference
        labels (fewer than 3 non-ground points), as the paper's annotators got road regions
        pre-labelled by a cell-based method. On a street map most occupied pillars are such
        plain road, so the CNN runs on a small part of the grid, and cannot mistake a road
        pillar beside a car for the car."""
        return np.flatnonzero(self.object_points >= self.config.min_object_points)

    @property
    def channels(self) -> int:
        """Input channels the map can give: counts, and passes when it has them."""
        return 1 if self.passes is None else 2

    def dense_block(self, vx0: int, vy0: int, nx: int, ny: int) -> np.ndarray:
        """(Z, nx, ny) float32 counts of voxels vx0..vx0+nx-1, vy0..vy0+ny-1 (zeros elsewhere)."""
        return self.channel_block(vx0, vy0, nx, ny, passes=False)[0]

    def channel_block(
        self, vx0: int, vy0: int, nx: int, ny: int, passes: bool = False
    ) -> np.ndarray:
        """(C, Z, nx, ny) float32 network input channels of the same voxels: counts, and with
        `passes` the distinct scanner passes (C = 2)."""
        if passes and self.passes is None:
            raise ValueError("this pillar map has no scanner passes (no point times)")
        block = np.zeros((2 if passes else 1, self.config.voxels_high, nx, ny), dtype=np.float32)
        a, b = np.searchsorted(self.vx, [vx0, vx0 + nx])
        vy = self.vy[a:b]
        sel = (vy >= vy0) & (vy < vy0 + ny)
        where = (self.vz[a:b][sel], self.vx[a:b][sel] - vx0, vy[sel] - vy0)
        block[0][where] = self.counts[a:b][sel]
        if passes:
            block[1][where] = self.passes[a:b][sel]  # type: ignore[index]
        return block

    def band_block(self, px0: int, py0: int, nx: int, ny: int, bands: int = 6) -> np.ndarray:
        """(bands, nx, ny) float32 point counts per pillar px0.., py0.. and height band (the
        pillar's voxel columns summed in `bands` equal slices: 0.5 m each by default)."""
        per, z = self.config.voxels_per_cell, self.config.voxels_high
        if z % bands:
            raise ValueError(f"{z} voxels per column do not split into {bands} bands")
        block = self.dense_block(px0 * per, py0 * per, nx * per, ny * per)
        return block.reshape(bands, z // bands, nx, per, ny, per).sum(axis=(1, 3, 5))


def phantom_ground(xyz: np.ndarray, config: PhantomConfig) -> GroundModel:
    """The ground the phantom pipeline measures heights from (runs, training, evaluation alike),
    with a grid margin so that a tile's window gets the ground of the whole map
    (`estimate_ground`'s `margin`)."""
    return estimate_ground(
        xyz, config.ground_cell, config.ground_opening, margin=config.ground_opening
    )


def build_pillar_map(
    xyz: np.ndarray,
    ground: GroundModel,
    config: PhantomConfig,
    passes: np.ndarray | None = None,
) -> PillarMap:
    """Voxelise the points between `below_ground` under and `pillar_height` above the ground;
    with `passes` (per point scanner pass) also count distinct passes per voxel."""
    v = config.voxel_size
    height = xyz[:, 2] - ground.height(xyz)
    layer = (height >= -config.below_ground) & (height < config.pillar_height)
    idx = np.flatnonzero(layer)
    vx = np.floor(xyz[idx, 0] / v).astype(np.int64)
    vy = np.floor(xyz[idx, 1] / v).astype(np.int64)
    vz = np.clip(np.floor(height[idx] / v).astype(np.int64), 0, config.voxels_high - 1)
    if len(idx) and (np.abs(vx).max() >= _BIAS or np.abs(vy).max() >= _BIAS):
        raise ValueError("coordinates beyond +-13,000 km: re-centre the map first")
    # one int64 per voxel: 28 bits vx, 28 bits vy, 5 bits vz (sorted by vx, then vy, then vz)
    key = (vx + _BIAS) << 33 | (vy + _BIAS) << 5 | vz
    keys, counts = np.unique(key, return_counts=True)
    voxel_passes = None if passes is None else _distinct_passes(key, keys, passes[idx])
    ux, uy, uz = (keys >> 33) - _BIAS, ((keys >> 5) & 0xFFFFFFF) - _BIAS, keys & 0x1F
    per = config.voxels_per_cell
    pkey = (vx // per + _BIAS) << 32 | (vy // per + _BIAS)
    pkeys, inverse = np.unique(pkey, return_inverse=True)
    pillars = np.stack([(pkeys >> 32) - _BIAS, (pkeys & 0xFFFFFFFF) - _BIAS], axis=1)
    point_pillar = np.full(len(xyz), -1, dtype=np.int64)
    point_pillar[idx] = inverse
    above = height[idx] > config.ground_tolerance
    object_points = np.bincount(inverse[above], minlength=len(pillars)).astype(np.int64)
    return PillarMap(
        config,
        ux,
        uy,
        uz,
        counts.astype(np.float32),
        pillars,
        point_pillar,
        height,
        object_points,
        voxel_passes,
    )


def _distinct_passes(key: np.ndarray, keys: np.ndarray, passes: np.ndarray) -> np.ndarray:
    """(M,) float32 distinct passes per voxel of the sorted voxel keys `keys`."""
    order = np.lexsort((passes, key))
    k, p = key[order], np.asarray(passes)[order]
    first = np.ones(len(k), dtype=bool)
    first[1:] = (k[1:] != k[:-1]) | (p[1:] != p[:-1])
    voxel = np.searchsorted(keys, k[first])
    return np.bincount(voxel, minlength=len(keys)).astype(np.float32)


def window_origin(pillar: np.ndarray, config: PhantomConfig) -> np.ndarray:
    """First voxel (vx, vy) of the CNN input of each pillar: its 11 x 11 pillar neighbourhood
    plus one voxel of context on every side (the first convolution's border, see network.py)."""
    half = config.neighbourhood // 2
    return np.asarray(pillar) * config.voxels_per_cell - half * config.voxels_per_cell - 1
