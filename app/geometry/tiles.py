"""Tiles along the trajectory: a survey of any length cut into pieces one worker can hold.

A tile is a stretch `[start, end)` of the trajectory's arc length (its *station*). Every point
belongs to exactly one tile, the tile of its station: the arc length at its foot on the
trajectory polyline (the place the vehicle was when it passed the point); `io.tile_index` takes
the station of the centre of the point's grid cell, so that a cell has one owner. A pipeline reads a
tile with a *halo*, the context its steps look at (the phantom CNN's window and vote, DUFOMap's
reach, a guardrail unit), computes there, and keeps only the results of the points the tile
owns: with a halo at least as wide as that context, tiled and untiled results agree.

The halo is spatial, not a stretch of stations: the points within `halo` metres (horizontally)
of the tile's own points, found on a grid of `cell`-metre cells (`halo_cells`). Where a drive
comes back to a place (a loop, the way back), points of the same street belong to tiles far
apart in station, and each still sees the other's points as context.

Stations are measured in the horizontal plane: the vehicle's height changes little along a
street, and a point's foot must not jump between the sweeps of a steep ramp.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from app.geometry.trajectory import StationIndex


def _flat(xy: np.ndarray) -> np.ndarray:
    """(N, 3) float64 with z = 0 from positions (N, 2 or more): stations are horizontal."""
    xy = np.asarray(xy, dtype=np.float64)
    xy = xy.reshape(len(xy), xy.shape[-1] if xy.ndim > 1 else -1)[:, :2]  # (0, 3) stays 2D
    return np.column_stack([xy, np.zeros(len(xy))])


# tiles evened over the workers (`TileLayout.along`) are at most this times the length asked:
# the nearest multiple of the workers (at least one multiple) is at least the tile count less
# half the workers
EVEN_STRETCH = 1.5


@dataclass(frozen=True)
class TileLayout:
    """Tiles of at most `length` metres along a trajectory, each read with `halo` metres around.
    `edges` are the stations where tiles start: every `length` metres (`along`), or closer
    where the points are dense (`cut_by_points`)."""

    stations_of: StationIndex | None  # the trajectory's station index; None: one position
    length: float
    halo: float
    edges: tuple[float, ...] = (0.0,)  # ascending start stations, the first 0

    @classmethod
    def along(
        cls,
        trajectory: np.ndarray,
        length: float,
        halo: float,
        workers: int | None = None,
    ) -> TileLayout:
        """The layout of a trajectory (M, 2 or 3) in driving order: tiles every `length` m.

        With `workers` (how many tiles run at once), a count of more than one becomes the
        multiple of `workers` nearest to it (half-way: the fewer), and the tiles equal: a short
        survey's 100, 100 and 40 m on two workers ran its last tile alone while the other
        worker idled; two tiles of 120 m keep both busy. Rounding up instead (four of 60 m)
        cost more than it saved (phantom and guardrail, 0.25 km): each tile reads its halo
        again. Evened tiles are at most `EVEN_STRETCH` times `length` (a job's memory
        estimate counts with that), and the layout's `length` is theirs (`equal`)."""
        if not length > 0 or not halo >= 0:
            raise ValueError(f"tile length {length} must be > 0 and halo {halo} >= 0")
        if len(trajectory) == 0:
            raise ValueError("a tile layout needs a trajectory of at least one position")
        positions = _flat(trajectory)
        index = StationIndex(positions) if len(positions) > 1 else None
        total = 0.0 if index is None else index.length
        count = max(int(np.ceil(total / length - 1e-9)), 1)
        if count == 1 or workers is None:
            return cls(index, float(length), float(halo), tuple(np.arange(count) * float(length)))
        share = max(int(workers), 1)
        count = max(int(np.ceil(count / share - 0.5)), 1) * share  # nearest, half-way down
        return cls(index, float(length), float(halo)).equal(count)

    def equal(self, count: int) -> TileLayout:
        """The same trajectory in `count` equal tiles, whose length the layout keeps: later
        cuts (by points, by budget) cut with it."""
        even = self.total / count
        return replace(self, length=even, edges=tuple(np.arange(count) * even))

    def cut_by_points(
        self, station: np.ndarray, points: np.ndarray, max_points: int, min_length: float
    ) -> TileLayout:
        """The same trajectory with tiles whose window (the tile and its halo, along the
        stations) holds at most about `max_points` points: `points[k]` points lie at
        `station[k]` (e.g. per grid cell). A tile ends where it reaches `length` metres or its
        window `max_points` points, whichever comes first, but is never shorter than
        `min_length` (where the halo alone holds more, the tile is as short as it may be)."""
        order = np.argsort(station, kind="stable")
        at = np.asarray(station, dtype=np.float64)[order]
        cumulative = np.r_[0, np.cumsum(np.asarray(points, dtype=np.int64)[order])]

        def before(s: float) -> int:  # points at stations below s
            return int(cumulative[np.searchsorted(at, s, side="left")])

        edges, start = [0.0], 0.0
        while True:  # one step per tile
            budget = before(start - self.halo) + max_points
            full = int(np.searchsorted(cumulative, budget, side="right")) - 1  # first over
            end = start + self.length
            if full < len(at):
                end = min(end, max(float(at[full]) - self.halo, start + min_length))
            if end >= self.total - 1e-9:
                break
            edges.append(end)
            start = end
        return TileLayout(self.stations_of, self.length, self.halo, tuple(edges))

    def balanced(self, station: np.ndarray, cost: np.ndarray, max_length: float) -> TileLayout:
        """The same trajectory in as many tiles, their edges moved so that each tile's window
        (the tile and its halo, along the stations) holds about the same `cost`: `cost[k]` lies
        at `station[k]` (a frame's or a cell's points). Equal lengths leave a built-up tile
        working while an open-road one is done: on two workers the survey waits for the
        slower. No tile grows past `max_length`; where that leaves the survey uncovered, the
        layout is returned as it was."""
        count = self.count
        if count < 2:
            return self
        order = np.argsort(station, kind="stable")
        at = np.asarray(station, dtype=np.float64)[order]
        cumulative = np.r_[0.0, np.cumsum(np.asarray(cost, dtype=np.float64)[order])]

        def start_of(s: float) -> float:  # cost at stations below s
            return float(cumulative[np.searchsorted(at, s, side="left")])

        def edges_within(most: float) -> tuple[float, ...] | None:
            """Tiles each as long as their window holds at most `most`; None: more needed."""
            edges = [0.0]
            for _ in range(count - 1):
                start = edges[-1]
                over = int(np.searchsorted(cumulative, start_of(start - self.halo) + most, "right"))
                end = min(float(at[over - 1]) - self.halo if over <= len(at) else np.inf,
                          start + max_length)  # fmt: skip
                if end <= start:
                    return None
                if end >= self.total:
                    return tuple(edges)  # fewer tiles than asked cover it: not balanced
                edges.append(end)
            last = edges[-1]
            fits = (
                self.total - last <= max_length
                and start_of(np.inf) - start_of(last - self.halo) <= most
            )
            return tuple(edges) if fits else None

        low, high = 0.0, float(cumulative[-1])
        if edges_within(high) is None:
            return self
        for _ in range(40):  # bisection on the most a window holds
            middle = 0.5 * (low + high)
            low, high = (low, middle) if edges_within(middle) is not None else (middle, high)
        edges = edges_within(high)
        if edges is None or len(edges) != count:
            return self
        return replace(self, edges=edges)

    def halved(self, tiles: list[int], min_length: float) -> TileLayout:
        """The same layout with each of `tiles` cut in two halves, where the halves are at least
        `min_length` long (a window that holds more than its stations say, e.g. where the drive
        comes back along a street, is cut again after `cut_by_points`)."""
        ends = [*self.edges[1:], self.total]
        middles = [
            0.5 * (self.edges[t] + ends[t])
            for t in tiles
            if ends[t] - self.edges[t] >= 2 * min_length
        ]
        return replace(self, edges=tuple(sorted([*self.edges, *middles])))

    @property
    def total(self) -> float:
        """Metres of trajectory."""
        return 0.0 if self.stations_of is None else self.stations_of.length

    @property
    def count(self) -> int:
        """Number of tiles (at least one; the last may be shorter)."""
        return len(self.edges)

    def bounds(self, tile: int) -> tuple[float, float]:
        """[start, end) stations the tile owns; the first and last tiles own everything before
        and after the trajectory too."""
        if not 0 <= tile < self.count:
            raise IndexError(f"tile {tile} of {self.count}")
        start = -np.inf if tile == 0 else self.edges[tile]
        end = np.inf if tile == self.count - 1 else self.edges[tile + 1]
        return float(start), float(end)

    def stations(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) station of each point (N, 2 or 3): the horizontal arc length at its foot on the
        trajectory (`geometry.trajectory.StationIndex`; before the start or past the end the
        stations run below 0 or past the total)."""
        if self.stations_of is None:
            return np.zeros(len(xyz))
        return self.stations_of.query(_flat(xyz))[0]

    def owner(self, station: np.ndarray) -> np.ndarray:
        """(N,) int64 tile owning each station."""
        k = np.searchsorted(np.asarray(self.edges), np.asarray(station, np.float64), "right") - 1
        return np.clip(k, 0, self.count - 1).astype(np.int64)


def cell_keys(xy: np.ndarray, cell: float) -> np.ndarray:
    """(N,) int64 key of the `cell`-metre grid cell of each horizontal position (N, >= 2)."""
    ij = np.floor(np.asarray(xy, dtype=np.float64)[:, :2] / cell).astype(np.int64)
    return _key(ij[:, 0], ij[:, 1])


_OFFSET = np.int64(1 << 30)  # cell indices within +-2^30 (10^6 km at 1 m cells)
_SPAN = np.int64(2) * _OFFSET  # keys stay below 2^62


def _key(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    return (i + _OFFSET) * _SPAN + (j + _OFFSET)


def cell_indices(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) grid indices of cell keys (`cell_keys`)."""
    key = np.asarray(key, dtype=np.int64)
    return key // _SPAN - _OFFSET, key % _SPAN - _OFFSET


def halo_cells(keys: np.ndarray, halo: float, cell: float) -> np.ndarray:
    """Sorted unique keys of the cells within `halo` metres of the cells `keys` (themselves
    included): a square dilation by ceil(halo / cell) cells, a superset of the true halo."""
    r = int(np.ceil(halo / cell))
    i, j = cell_indices(np.unique(keys))
    di, dj = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
    ii = (i[:, None] + di.ravel()[None, :]).ravel()
    jj = (j[:, None] + dj.ravel()[None, :]).ravel()
    return np.unique(_key(ii, jj))
