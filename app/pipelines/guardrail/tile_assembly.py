"""A tiled guardrail run's outputs, assembled from its tiles' files (`tiled`) as they finish.

While tiles run: each tile's guardrail points go into the frames' label files on disk, its LAZ
part is appended in tile order (`tiling.TileMaps`), and what ties its components to its
neighbours' is kept. Once all are in:

- **Components across tiles.** A tile numbers its components itself. Two components of
  neighbouring tiles that hold the same point (within `LINK_BAND` of their common edge, which
  both tiles see) are one; every slice gets the run's component number. Slice keys
  (component, slice index) stay unique: where two of a tile's components turn out to be one
  and both have a slice at one station, the second keeps a number of its own.
- **Guardrails** are then grouped, joined and reconstructed from the guardrail slices of all
  tiles (`pipeline.rebuild_guardrails`): a rail is one model from its first pole to its last.
  The grouping reads the slices only (`save_rails`: an index of the tiles' parts); each
  guardrail's points are then read for it alone, its meshes written and let go.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from app.metrics.classification import binary_from_counts
from app.pipelines.guardrail.pipeline import ReconstructionInput
from app.pipelines.guardrail.segmentation import index_slice_features
from app.pipelines.outputs import commit_frame_labels, fill_labels_of_frames, start_frame_labels
from app.pipelines.tiling import TILES, TileMaps, tile_name, tile_totals

SLICE_COLUMNS = ("component", "slice_index", "station", "probability", "raw", "corrected",
                 "has_crop")  # fmt: skip
RAILS = "guardrail_points"  # the LAZ of the points on guardrails, OUT/guardrail_points.laz
RAILS_INDEX = "rails.npz"  # OUT/tiles/: the guardrail slices of every tile, points in the parts
LINKS = ("start_keys", "start_components", "end_keys", "end_components")


@dataclass
class SliceTable:
    """Every slice of the run, in tile order: its key and the classifier's decisions."""

    component: np.ndarray  # (K,) int64 the run's component number
    slice_index: np.ndarray  # (K,) int64 station index of the slice
    station: np.ndarray  # (K,) float64
    probability: np.ndarray  # (K,) float64
    raw: np.ndarray  # (K,) bool
    corrected: np.ndarray  # (K,) bool
    has_crop: np.ndarray  # (K,) bool

    def __len__(self) -> int:
        return len(self.component)


class GuardrailAssembly:
    """Frame labels and the guardrail points' LAZ while tiles finish; the slices, components
    and guardrail stage once they are all in (`finish`)."""

    def __init__(self, out: Path, frame_ids: list[str], frame_sizes: np.ndarray):
        self.out, self.folder, self.frame_ids = Path(out), Path(out) / TILES, frame_ids
        start_frame_labels(self.out, dict(zip(frame_ids, frame_sizes.tolist(), strict=True)))
        self.maps = TileMaps(self.out, (RAILS,))
        self.links: dict[int, dict[str, np.ndarray]] = {}
        self.columns: dict[int, dict[str, np.ndarray]] = {}

    def add(self, summary: dict) -> None:
        tile = int(summary["tile"])
        with np.load(self.folder / f"{tile_name(tile)}.npz") as data:
            frame, index = data["rail_frame"], data["rail_index"]
            ones = np.ones(len(frame), dtype=np.uint8)
            fill_labels_of_frames(self.out, self.frame_ids, frame, index, ones)
            self.links[tile] = {key: data[key] for key in LINKS}
            self.columns[tile] = {key: data[key] for key in SLICE_COLUMNS}
        self.maps.add(summary)

    def finish(self) -> dict:
        """The files completed and the slices numbered; returns {"files", "slices" (SliceTable),
        "numbers" (per tile, the run's component of each of its slices), "counts",
        "metric_counts", "timings", "worker_peak_mb"}."""
        commit_frame_labels(self.out, self.frame_ids)
        written = self.maps.close()
        files = {RAILS: f"{RAILS}.laz"} if written[RAILS] else {}
        summaries = [self.maps.summaries[t] for t in sorted(self.maps.summaries)]
        tiles = [int(s["tile"]) for s in summaries]
        numbers = slice_components(
            [int(s["components"]) for s in summaries],
            [self.links[t] for t in tiles],
            [self.columns[t]["component"] for t in tiles],
            [self.columns[t]["slice_index"] for t in tiles],
        )
        joined = {
            key: np.concatenate([self.columns[t][key] for t in tiles]) for key in SLICE_COLUMNS
        }
        joined["component"] = np.concatenate(numbers) if numbers else np.zeros(0, np.int64)
        table = SliceTable(**{k: np.asarray(v) for k, v in joined.items()})
        return {"files": files, "slices": table, "numbers": dict(zip(tiles, numbers, strict=True)),
                **_totals(summaries)}  # fmt: skip

    def abort(self) -> None:
        self.maps.abort()

    def save_rails(self, numbers: dict[int, np.ndarray]) -> Path | None:
        """An index of the tiles' guardrail slices (their points stay in the tiles' parts), with
        the run's component numbers: what the guardrails are grouped and built from, one at a
        time (`pipeline.rebuild_guardrails`). None without tiles."""
        if not numbers:
            return None
        tiles = sorted(numbers)
        parts = [self.folder / f"{tile_name(t)}.rails.npz" for t in tiles]
        owned = [numbers[t][self.columns[t]["corrected"].astype(bool)] for t in tiles]
        return ReconstructionInput.save_parts(self.folder / RAILS_INDEX, parts, owned)

    def save_stage(self, path: Path, numbers: dict[int, np.ndarray]) -> Path:
        """An index of the tiles' stage parts (every slice, with the run's component numbers;
        the points stay in the parts, under the run's folder)."""
        tiles = sorted(numbers)
        parts = [self.folder / f"{tile_name(t)}.stage.npz" for t in tiles]
        return ReconstructionInput.save_parts(path, parts, [numbers[t] for t in tiles])

    def features(self, path: Path, numbers: dict[int, np.ndarray]) -> Path:
        """An index of the tiles' classifier inputs (what retraining reads: the features stay in
        the tiles' files), keyed by the run's component numbers."""
        tiles = sorted(numbers)
        parts = [self.folder / f"{tile_name(t)}.features.npz" for t in tiles]
        return index_slice_features(path, parts, [numbers[t] for t in tiles])


def slice_components(
    counts: list[int],
    links: list[dict[str, np.ndarray]],
    components: list[np.ndarray],
    slice_index: list[np.ndarray],
) -> list[np.ndarray]:
    """Per tile, the run's component number of each of its slices (see the module docstring):
    `counts` components per tile, `links` their points at the tile's edges, `components` and
    `slice_index` the tile's slices' own component and station index."""
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    first, second = [], []
    for t in range(len(counts) - 1):  # a tile's end against the next tile's start
        a, b = links[t], links[t + 1]
        _, ia, ib = np.intersect1d(a["end_keys"], b["start_keys"], return_indices=True)
        first.append(offsets[t] + a["end_components"][ia])
        second.append(offsets[t + 1] + b["start_components"][ib])
    n = int(offsets[-1])
    i = np.concatenate(first) if first else np.zeros(0, np.int64)
    j = np.concatenate(second) if second else np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(len(i), dtype=np.int8), (i, j)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    # numbered in order of first appearance: tile by tile, as the tiles number their own
    _, first_seen = np.unique(label, return_index=True)
    rank = np.empty(len(first_seen), dtype=np.int64)
    rank[np.argsort(first_seen)] = np.arange(len(first_seen))
    number = rank[label] if n else np.zeros(0, np.int64)
    out = [number[offsets[t] + np.asarray(c, np.int64)] for t, c in enumerate(components)]
    # two slices with one key (components joined through other tiles): the later ones apart
    if out:
        keys = np.stack([np.concatenate(out), np.concatenate(slice_index)], axis=1)
        _, keep = np.unique(keys, axis=0, return_index=True)
        twice = np.setdiff1d(np.arange(len(keys)), keep)
        flat = np.concatenate(out)
        flat[twice] = n + np.arange(len(twice))
        out = np.split(flat, np.cumsum([len(c) for c in out])[:-1])
    return out


def _totals(summaries: list[dict]) -> dict:
    keys = ("points", "slices", "slices_with_crop", "guardrail_slices", "guardrail_points")
    counts = {key: sum(int(s[key]) for s in summaries) for key in keys}
    metric_counts = None
    for s in summaries:
        if s["metric_counts"] is not None:
            metric_counts = add_metric_counts(metric_counts, s["metric_counts"])
    return {"counts": counts, "metric_counts": metric_counts, **tile_totals(summaries)}


def add_metric_counts(total: dict | None, part: dict) -> dict:
    """Two tiles' confusion counts added."""
    if total is None:
        return {k: (list(v) if isinstance(v, list) else v) for k, v in part.items()}
    return {
        k: [a + b for a, b in zip(v, part[k], strict=True)] if isinstance(v, list) else v + part[k]
        for k, v in total.items()
    }


def slice_metrics_from_counts(counts: dict, slices: int) -> dict:
    """The report's scores (as `run.slice_metrics` gives them for a whole run) from the
    tiles' added confusion counts."""
    return {
        "slices": slices,
        "reference_guardrail_slices": int(counts["reference_guardrail_slices"]),
        **{k: binary_from_counts(*counts[k]).as_dict() for k in ("slice_raw", "slice", "point")},
    }
