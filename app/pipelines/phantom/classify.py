"""Pillar classification: the per-window reference path and the dense (fully-convolutional)
path that shares the convolutions of overlapping windows, tiled with a halo so memory stays
bounded on any map size. Both return softmax probabilities (len(which), 4) for the pillars
`which` (indices into `pm.pillars`, default all occupied pillars)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from app.pipelines.phantom.network import CONTEXT_BANDS, CONTEXT_SPAN, PillarCNN, dense_logits
from app.pipelines.phantom.pillars import PillarMap, window_origin

FractionDone = Callable[[float], None]  # inside one stage: the stage reports it as Progress


def window_tensor(pm: PillarMap, pillars: np.ndarray, passes: bool = False) -> torch.Tensor:
    """(N, C, 30, 24, 24) inputs of the given pillars (their windows plus one context voxel):
    C = 1 point counts, or 2 with `passes` (counts and distinct scanner passes)."""
    side = pm.config.window_voxels + 2
    origins = window_origin(pillars, pm.config)
    lo = origins.min(axis=0)
    span = origins.max(axis=0) - lo + side
    block = pm.channel_block(int(lo[0]), int(lo[1]), int(span[0]), int(span[1]), passes)
    ox, oy = (origins - lo).T
    r = np.arange(side)
    windows = block[
        :, :, ox[:, None, None] + r[None, :, None], oy[:, None, None] + r[None, None, :]
    ]  # (C, Z, N, side, side)
    return torch.from_numpy(np.ascontiguousarray(windows.transpose(2, 0, 1, 3, 4)))


def band_tensor(pm: PillarMap, pillars: np.ndarray) -> torch.Tensor:
    """(N, 6, 31, 31) band counts of the pillars' surroundings (the context branch's input)."""
    half = CONTEXT_SPAN // 2
    lo = pillars.min(axis=0) - half
    span = pillars.max(axis=0) + half + 1 - lo
    block = pm.band_block(int(lo[0]), int(lo[1]), int(span[0]), int(span[1]), CONTEXT_BANDS)
    ox, oy = (pillars - half - lo).T
    r = np.arange(CONTEXT_SPAN)
    bands = block[:, ox[:, None, None] + r[None, :, None], oy[:, None, None] + r[None, None, :]]
    return torch.from_numpy(np.ascontiguousarray(bands.transpose(1, 0, 2, 3)))


def network_inputs(
    net: PillarCNN, pm: PillarMap, pillars: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What the network reads for each pillar: its window and, with a context branch, bands."""
    bands = band_tensor(pm, pillars) if net.context else None
    return window_tensor(pm, pillars, net.passes), bands


def _selected(pm: PillarMap, which: np.ndarray | None) -> np.ndarray:
    return np.arange(len(pm.pillars)) if which is None else np.asarray(which, dtype=np.int64)


@torch.no_grad()
def classify_windows(
    net: PillarCNN,
    pm: PillarMap,
    batch: int = 512,
    progress: FractionDone | None = None,
    which: np.ndarray | None = None,
) -> np.ndarray:
    """Reference path: each pillar's window through the network on its own."""
    net.eval()
    which = _selected(pm, which)
    out = np.zeros((len(which), 4), dtype=np.float32)
    for a in range(0, len(which), batch):
        x, bands = network_inputs(net, pm, pm.pillars[which[a : a + batch]])
        out[a : a + batch] = torch.softmax(net(x, bands), dim=1).numpy()
        if progress is not None:
            progress(min(a + batch, len(which)) / len(which))
    return out


@torch.no_grad()
def classify_dense(
    net: PillarCNN,
    pm: PillarMap,
    tile: int = 32,
    progress: FractionDone | None = None,
    which: np.ndarray | None = None,
) -> np.ndarray:
    """Dense path: tiles of `tile` x `tile` pillars, each computed fully-convolutionally from
    its block of voxels (tile + 5-pillar halo + context), only where there are pillars to
    classify."""
    net.eval()
    cfg = pm.config
    half, per = cfg.neighbourhood // 2, cfg.voxels_per_cell
    side = per * tile + cfg.window_voxels + 2
    which = _selected(pm, which)
    out = np.zeros((len(which), 4), dtype=np.float32)
    pillars = pm.pillars[which]
    tiles = np.floor_divide(pillars, tile)
    keys, inverse = np.unique(tiles, axis=0, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(keys) + 1))
    for k, (tx, ty) in enumerate(keys):
        members = order[bounds[k] : bounds[k + 1]]
        first = np.array([tx * tile - half, ty * tile - half])  # first window pillar P0
        v0 = first * per - 1
        block = pm.channel_block(int(v0[0]), int(v0[1]), side, side, net.passes)
        bands = None
        if net.context:  # surroundings of the tile's pillars tx * tile.., ty * tile..
            c0 = np.array([tx, ty]) * tile - CONTEXT_SPAN // 2
            bands = pm.band_block(int(c0[0]), int(c0[1]), tile + CONTEXT_SPAN - 1,
                                  tile + CONTEXT_SPAN - 1, CONTEXT_BANDS)  # fmt: skip
            bands = torch.from_numpy(bands)[None]
        logits = dense_logits(net, torch.from_numpy(block)[None], bands)
        local = pillars[members] - first - half
        probs = torch.softmax(logits[:, local[:, 0], local[:, 1]], dim=0)
        out[members] = probs.T.numpy()
        if progress is not None:
            progress((k + 1) / len(keys))
    return out
