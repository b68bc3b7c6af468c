"""A tiled clutter run's files assembled from its tiles' as they finish (`tiled.py`).

Each tile wrote its own frames' labels (OUT/labels/, final already), and under OUT/tiles/ its
LAZ parts, the observations of the tracks that touch its frames, and its summary (counts, error
matrices, review rows). Here the LAZ parts are appended in tile order (`io.las.LasAppender`),
the counts and error matrices summed, and the tracks joined: a track that crosses a tile border
was seen by both tiles, and the two share at least one observation (a frame's clusters are the
same in every tile that reads the frame), so tracks sharing an observation are one track.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from app.io.las import write_laz
from app.pipelines.clutter.evaluation.removal_metrics import add_removal_counts
from app.pipelines.tiling import MAPS, TILES, TileMaps, tile_name, tile_totals

# a (frame, cluster) observation as one integer: clusters per frame stay below 2^24
_CLUSTERS = np.int64(1 << 24)


class ClutterAssembly:
    """The run's maps, totals, tracks and review rows from the tiles' summaries, taken in any
    order while later tiles still run (the maps keep tile order)."""

    def __init__(self, out: Path):
        self.out, self.folder = Path(out), Path(out) / TILES
        self.maps = TileMaps(self.out)
        self.summaries = self.maps.summaries

    def add(self, summary: dict) -> None:
        self.maps.add(summary)

    def finish(self) -> dict:
        """The maps completed; returns {"files", "counts", "metric_counts", "timings",
        "worker_peak_mb", "segmentation", "rows"} (rows with joined track ids)."""
        files = {kind: f"{kind}.laz" for kind in MAPS}
        for kind, written in self.maps.close().items():
            if not written:  # no tile had a point of this map
                write_laz(self.out / files[kind], np.zeros((0, 3)))
        tiles = sorted(self.summaries)
        track_of = join_tracks(self.folder, tiles)
        counts = {"frames": 0, "points": 0, "points_in_view": 0, "removed_points": 0,
                  "map_points": 0}  # fmt: skip
        metric_counts, rows = None, []
        for tile in tiles:
            s = self.summaries[tile]
            for key in counts:
                counts[key] += s["counts"][key]
            if s["metric_counts"] is not None:
                metric_counts = add_removal_counts(metric_counts, s["metric_counts"])
            for row in s["rows"]:
                local = row["track_id"]
                rows.append({**row, "track_id": None if local is None else track_of[tile][local]})
        counts["tracks"] = int(max((max(t.values(), default=-1) for t in track_of.values()),
                                   default=-1) + 1)  # fmt: skip
        return {
            "files": files, "counts": counts, "metric_counts": metric_counts,
            **tile_totals([self.summaries[t] for t in tiles]),
            "segmentation": {key: sum(s["segmentation"][key] for s in self.summaries.values())
                             for key in ("cache_hits", "segmented")},
            "rows": rows,
        }  # fmt: skip

    def abort(self) -> None:
        self.maps.abort()


def join_tracks(folder: Path, tiles: list[int]) -> dict[int, dict[int, int]]:
    """{tile: {its track id: the run's track id}}: tracks of different tiles that share an
    observation (frame, cluster) are one track; ids follow the tiles' order."""
    nodes, keys, local = [], [], []
    for tile in tiles:
        with np.load(folder / f"{tile_name(tile)}.tracks.npz") as data:
            track, frame, cluster = data["track"], data["frame"], data["cluster"]
        ids = np.unique(track)
        nodes.append(np.column_stack([np.full(len(ids), tile), ids]))
        base = sum(len(n) for n in nodes[:-1])
        local.append(base + np.searchsorted(ids, track))
        keys.append(frame * _CLUSTERS + cluster)
    if not nodes:
        return {}
    node = np.concatenate(local)
    key = np.concatenate(keys)
    count = sum(len(n) for n in nodes)
    order = np.argsort(key, kind="stable")
    same = np.flatnonzero(key[order][1:] == key[order][:-1])  # consecutive equal observations
    a, b = node[order][same], node[order][same + 1]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(count, count))
    _, component = connected_components(graph, directed=False)
    # number the joined tracks in order of their first node (tile order, then local id)
    _, first = np.unique(component, return_index=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    joined = rank[np.unique(component, return_inverse=True)[1]]
    pairs = np.concatenate(nodes) if count else np.zeros((0, 2), dtype=np.int64)
    out: dict[int, dict[int, int]] = {int(t): {} for t in tiles}
    for (tile, track), run_id in zip(pairs.tolist(), joined.tolist(), strict=True):
        out[tile][track] = run_id
    return out
