"""The labelling view's click tools besides the brush, as geometry on arrays:

- Fill: the pillars connected to the clicked one through neighbours (bridging one empty
  pillar) whose top heights differ by at most a step (a magic wand over the pillar grid: a road
  with camber or a slope fills whole, a kerb or a car's flank stops it), within a radius of the
  click.
- Polygon: vertices picked in 3D (so the polygon survives camera moves), projected with the
  camera at closing time; the shown points inside it (and visible, as for the rectangle) give
  the pillars. CloudCompare's segmentation polygon; the free-hand lasso (`pillars.py`, a
  Ctrl-drag) tests its path the same way.
- Measure: the distance between two picked points (3D, horizontal, vertical).
- Inspect: one point's coordinates and attributes.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from app.store.pillar_labels import STORE_GRID

FILL_STEP = 0.08  # metres: the largest top-height step between neighbours (a kerb: 0.1-0.2)
FILL_RADIUS = 40.0  # metres from the seed: a fill stays local
REACH = 2  # pillars: neighbours up to two pillars away, so a fill crosses a one-pillar gap
# (sparse scans leave empty pillars between occupied ones); each neighbour pair once
NEIGHBOURS = tuple(
    (dx, dy) for dx in range(REACH + 1) for dy in range(-REACH, REACH + 1) if dx > 0 or dy > 0
)


def pillar_tops(
    cells: np.ndarray, pillar: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(store cell ids, the highest z of each) of the pillars holding points; `pillar`: each
    point's index into `cells` (the map's sorted pillars), so the tops are gathered in an
    array over the map's pillars, not by sorting the points (a fill reads 400,000)."""
    top = np.full(len(cells), -np.inf)
    np.maximum.at(top, pillar, z)
    present = np.flatnonzero(top > -np.inf)
    return cells[present], top[present]


def fill_region(
    cells: np.ndarray, top: np.ndarray, seed: int, step: float = FILL_STEP
) -> np.ndarray:
    """Store cell ids of the pillars connected to `seed` (a cell id in `cells`, sorted) through
    neighbours (up to REACH pillars away) whose tops differ by at most `step`: the pillars go
    into a raster of their bounding box, each neighbour pair of it is an edge when both hold a
    pillar and their tops are close, and the seed's connected component is the fill."""
    at = int(np.searchsorted(cells, seed))
    if at >= len(cells) or cells[at] != seed:
        return np.zeros(0, dtype=np.int64)
    ix, iy = (np.asarray(a, dtype=np.int64) for a in STORE_GRID.decode(cells))
    ix, iy = ix - ix.min(), iy - iy.min()
    shape = (int(ix.max()) + 1, int(iy.max()) + 1)
    index = np.full(shape, -1, dtype=np.int64)
    index[ix, iy] = np.arange(len(cells))
    height = np.full(shape, np.nan)
    height[ix, iy] = top
    rows, cols = [], []
    for dx, dy in NEIGHBOURS:
        a = (slice(0, shape[0] - dx), slice(max(-dy, 0), shape[1] - max(dy, 0)))
        b = (slice(dx, shape[0]), slice(max(dy, 0), shape[1] - max(-dy, 0)))
        close = np.abs(height[a] - height[b]) <= step  # NaN (no pillar) compares False
        rows.append(index[a][close])
        cols.append(index[b][close])
    i, j = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(i), dtype=np.int8), (i, j)), shape=(len(cells),) * 2)
    _, component = connected_components(graph, directed=False)
    return cells[component == component[at]]


def points_in_polygon(uv: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(n,) bool: screen points `uv` (n, 2) inside the closed `polygon` (k, 2), even-odd rule.
    The points sorted by row once, each edge tests only those whose row it spans (a contiguous
    run of the sorted points): a free-hand lasso has hundreds of edges, a street 100,000 points,
    and a row of the screen crosses only a few edges."""
    uv = np.asarray(uv, dtype=np.float64)
    poly = np.asarray(polygon, dtype=np.float64)
    order = np.argsort(uv[:, 1], kind="stable")
    u, v = uv[order, 0], uv[order, 1]
    inside = np.zeros(len(uv), dtype=bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        if a[1] == b[1]:
            continue  # a level edge crosses no row
        # the edge crosses the rows v with min <= v < max (one end above v, the other not)
        first, stop = np.searchsorted(v, sorted((a[1], b[1])), side="left")
        run = slice(first, stop)
        x = a[0] + (v[run] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        inside[run] ^= u[run] < x
    result = np.zeros(len(uv), dtype=bool)
    result[order] = inside
    return result


def measure_text(a: np.ndarray, b: np.ndarray) -> str:
    d = np.asarray(b, dtype=np.float64) - np.asarray(a, dtype=np.float64)
    return (
        f"Distance **{np.linalg.norm(d):.2f} m** (horizontal {np.hypot(d[0], d[1]):.2f} m, "
        f"vertical {d[2]:+.2f} m)"
    )
