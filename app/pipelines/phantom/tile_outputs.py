"""A tiled phantom run's files: each tile's results kept under OUT/tiles/ the moment it
finishes, and the contract's files assembled from them without holding the survey.

Per tile (written by whichever worker ran it; the folder must be shared with a cluster's
workers): `NNNNN.npz` (its own points' frame, index and label; its own pillars' grid cells,
posteriors and labels), `NNNNN.cleaned.laz` / `NNNNN.removed.laz`, and last `NNNNN.json`,
its summary (resuming: `pipelines.tiling`). Assembly (`Assembly`, while later tiles still
run): labels per frame filled on disk (`outputs.start_frame_labels`), the LAZ parts appended to
one file each in tile order (`io.las.LasAppender`), the pillars joined.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.core.labels import PillarClass
from app.io.asprs import PHANTOM_LABEL_TO_ASPRS, to_asprs
from app.io.las import write_laz
from app.pipelines.outputs import (
    commit_frame_labels,
    fill_labels_of_frames,
    start_frame_labels,
)
from app.pipelines.phantom.evaluation.classification_metrics import add_counts
from app.pipelines.phantom.point_labels import kept
from app.pipelines.tiling import (
    MAPS,
    TILES,
    TileMaps,
    save_tile_arrays,
    tile_name,
    tile_totals,
    write_summary,
)


@dataclass
class TileResult:
    """What one tile found for the points and pillars it owns."""

    tile: int
    frame: np.ndarray  # (n,) int64 frame index in the survey
    index: np.ndarray  # (n,) int64 point index in its frame
    xyz: np.ndarray  # (n, 3) float64
    labels: np.ndarray  # (n,) uint8 pillar class
    in_layer: int  # of the n points, in the pillar layer
    pillars: dict[str, np.ndarray] = field(default_factory=dict)  # the pillars.npz columns
    metric_counts: dict | None = None  # additive metrics (reference labels present)
    timings: dict[str, float] = field(default_factory=dict)
    peak_mb: float = 0.0  # the peak resident memory of the process that ran it, so far


def write_tile(out: Path, result: TileResult, offset: np.ndarray) -> dict:
    """The tile's files, its summary last (what marks it done); returns the summary."""
    folder = Path(out) / TILES
    name = tile_name(result.tile)
    save_tile_arrays(
        out, result.tile, frame=result.frame, index=result.index, labels=result.labels,
        **{f"pillar_{k}": v for k, v in result.pillars.items()},
    )  # fmt: skip
    keep = kept(result.labels)
    maps = {}
    for kind, which in zip(MAPS, (keep, ~keep), strict=True):
        if which.any():
            write_laz(
                folder / f"{name}.{kind}.laz",
                result.xyz[which],
                mmsclean_label=result.labels[which],
                classification=to_asprs(result.labels[which], PHANTOM_LABEL_TO_ASPRS),
                source_frame=result.frame[which],
                source_index=result.index[which],
                offset=offset,
            )
            maps[kind] = f"{name}.{kind}.laz"
    labels = result.labels
    pillar_labels = result.pillars.get("labels", np.zeros(0, dtype=np.uint8))
    return write_summary(out, result.tile, {
        "points": int(len(labels)),
        "points_in_layer": result.in_layer,
        "pillars": int(len(pillar_labels)),
        "pillars_classified": int(result.pillars.get("classified", np.zeros(0, bool)).sum()),
        "pillars_per_class": {c.name.lower(): int((pillar_labels == c).sum()) for c in PillarClass},
        "phantom_points": int((labels == PillarClass.phantom).sum()),
        "maps": maps,
        "metric_counts": result.metric_counts,
        "timings": result.timings,
        "worker_peak_mb": round(result.peak_mb, 1),
    })  # fmt: skip


class Assembly:
    """The contract's files built from the tiles' as they finish, while later tiles still run:
    each tile's labels go into the frames' label files on disk, its pillars are kept (a few
    bytes per pillar), and its LAZ parts are appended to cleaned.laz / removed.laz as soon as
    every tile before it is in (the maps keep tile order whatever order tiles finish in)."""

    def __init__(self, out: Path, frame_ids: list[str], frame_sizes: np.ndarray):
        self.out, self.folder, self.frame_ids = Path(out), Path(out) / TILES, frame_ids
        start_frame_labels(self.out, dict(zip(frame_ids, frame_sizes.tolist(), strict=True)))
        self.columns: dict[str, list[tuple[int, np.ndarray]]] = {}
        self.maps = TileMaps(self.out)

    def add(self, summary: dict) -> None:
        tile = int(summary["tile"])
        with np.load(self.folder / f"{tile_name(tile)}.npz") as data:
            fill_labels_of_frames(
                self.out, self.frame_ids, data["frame"], data["index"], data["labels"]
            )
            for key in data.files:
                if key.startswith("pillar_"):
                    self.columns.setdefault(key.removeprefix("pillar_"), []).append(
                        (tile, data[key])
                    )
        self.maps.add(summary)

    def finish(self) -> dict:
        """The files completed; returns {"files", "counts", "metric_counts", "timings",
        "worker_peak_mb"}."""
        commit_frame_labels(self.out, self.frame_ids)
        files = {kind: f"{kind}.laz" for kind, n in self.maps.close().items() if n}
        pillars = {
            key: np.concatenate([values for _, values in sorted(parts, key=lambda p: p[0])])
            for key, parts in self.columns.items()
        }
        cell_size = float(pillars.pop("cell_size")[0]) if "cell_size" in pillars else 0.0
        np.savez_compressed(self.out / "pillars.npz", cell_size=cell_size, **pillars)
        files["pillars"] = "pillars.npz"
        return {"files": files, **_totals(list(self.maps.summaries.values()))}

    def abort(self) -> None:
        self.maps.abort()


def _totals(summaries: list[dict]) -> dict:
    counts = {"points": 0, "points_in_layer": 0, "pillars": 0, "pillars_classified": 0,
              "phantom_points": 0}  # fmt: skip
    per_class = {c.name.lower(): 0 for c in PillarClass}
    metric_counts = None
    for s in summaries:
        for key in counts:
            counts[key] += s[key]
        for key, n in s["pillars_per_class"].items():
            per_class[key] += n
        if s["metric_counts"] is not None:
            metric_counts = add_counts(metric_counts, s["metric_counts"])
    counts["pillars_per_class"] = per_class
    return {"counts": counts, "metric_counts": metric_counts, **tile_totals(summaries)}
