"""A missed object from a 2D box drawn on the camera image (clutter review), as CVAT and
SUSTechPOINTS let an annotator add an object the detector missed: the box names the object, the
LiDAR points give its extent.

A box on an image holds the object and whatever the camera sees past it (a facade behind a
parked car), in front of it (a low wall) or under it (the road). So: the frame's ground is
estimated on all its points (a tight box holds little road) and the points more than the run's
`ground_tolerance` above it in the box and around it (the box grown by `AROUND` of its size on
every side) are clustered (the run's `cluster_voxel`, `clutter.clusters.frame_clusters`). Each
cluster scores the box's cells it is seen in (cells of `VOTE_CELL_PX`; in each the point
nearest the camera is the one seen there: an object hides what lies behind it inside its own
outline) times the square of the share of its points around the box that lie inside it (the
box was drawn round the object; a facade, a wall or a nearer truck runs on past it: squared, a
far car boxed beside a truck's edge is not lost to the truck's many cells) times how well its
own outline on the image fills the box (intersection over union: a pole or an advertising
column in front of a van is seen in many cells, but is narrower than the box drawn round the
van). The best is the object; its points in the box that belong to no instance are the new
object, unless at least `OWNED_SHARE` of them belong to instances already (then it is one:
nothing is added, never the facade behind it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.core.errors import ConfigError
from app.geometry.extents import label_extents
from app.geometry.projection import Projection
from app.io.survey import Camera, Survey
from app.pipelines.clutter.clusters import frame_clusters
from app.pipelines.clutter.config import ClutterConfig

VOTE_CELL_PX = 8  # pixels: a cell of the visible-surface vote (a few HDL-64E rings tall at 20 m)
OWNED_SHARE = 0.5  # an object this much in instances already is one: nothing to add
AROUND = 0.5  # share of the box's width and height by which it grows on each side: its context


@dataclass(frozen=True)
class PixelBox:
    """A box on the camera image in pixels: u (column) and v (row) from its top-left corner."""

    u0: float
    v0: float
    u1: float
    v1: float

    @classmethod
    def spanning(cls, a: tuple[float, float], b: tuple[float, float]) -> PixelBox:
        """The box with corners `a` and `b`, (u, v) each, in any order."""
        return cls(min(a[0], b[0]), min(a[1], b[1]), max(a[0], b[0]), max(a[1], b[1]))

    def clipped(self, width: int, height: int) -> PixelBox:
        return PixelBox(
            min(max(self.u0, 0.0), width), min(max(self.v0, 0.0), height),
            min(max(self.u1, 0.0), width), min(max(self.v1, 0.0), height),
        )  # fmt: skip

    @property
    def area(self) -> float:
        return max(self.u1 - self.u0, 0.0) * max(self.v1 - self.v0, 0.0)

    def holds(self, uv: np.ndarray) -> np.ndarray:
        """Whether each (u, v) lies inside (nan: outside)."""
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= self.u0) & (uv[:, 0] < self.u1)
                & (uv[:, 1] >= self.v0) & (uv[:, 1] < self.v1)
            )  # fmt: skip

    def grown(self, share: float) -> PixelBox:
        du, dv = share * (self.u1 - self.u0), share * (self.v1 - self.v0)
        return PixelBox(self.u0 - du, self.v0 - dv, self.u1 + du, self.v1 + dv)

    def as_bbox(self) -> list[int]:
        """[u0, v0, u1, v1] in whole pixels, as instances keep their image box."""
        return [int(np.floor(self.u0)), int(np.floor(self.v0)), int(np.ceil(self.u1)),
                int(np.ceil(self.v1))]  # fmt: skip


def _report_config(folder: Path | None) -> dict:
    """The config a clutter run's report records ({} without a readable one)."""
    if folder is None:
        return {}
    try:
        config = json.loads((folder / "report.json").read_text()).get("config")
    except (OSError, ValueError, AttributeError):
        return {}
    return config if isinstance(config, dict) else {}


def run_config(folder: Path | None) -> ClutterConfig:
    """The clutter run's own settings (its report), else the defaults: the box clusters as the
    run did."""
    try:
        return ClutterConfig(**_report_config(folder))
    except (TypeError, ValueError):  # pydantic's ValidationError is a ValueError
        return ClutterConfig()


def run_camera(survey: Survey, folder: Path | None) -> Camera | None:
    """The camera the run segmented (its report's config), else the survey's first."""
    config = _report_config(folder)
    name = config.get("camera") if config.get("use_camera", True) else None
    if name is None and survey.cameras:
        name = next(iter(survey.cameras))
    return survey.cameras.get(name) if name else None


def object_in_box(
    sensor_xyz: np.ndarray,
    projection: Projection,
    owner: np.ndarray,
    box: PixelBox,
    config: ClutterConfig,
) -> np.ndarray:
    """Frame indices of the object the box outlines: the points of the cluster the camera sees
    most inside the box, in the box, free of any instance (empty: nothing above the ground in
    the box, or the object seen there belongs to instances already: never the next one behind
    it)."""
    inside = projection.in_image & box.holds(projection.uv)
    if not inside.any():
        return np.zeros(0, dtype=np.int64)
    around = projection.in_image & box.grown(AROUND).holds(projection.uv)
    clusters = frame_clusters(
        sensor_xyz, config.cluster_voxel, config.ground_cell, config.ground_tolerance,
        config.max_range, subset=around,
    )  # fmt: skip
    label = clusters.label
    above = np.flatnonzero((label >= 0) & inside)
    if not len(above):
        return np.zeros(0, dtype=np.int64)
    seen = above[nearest_per_cell(projection.uv[above], projection.depth[above])]
    n = int(label.max()) + 1
    in_box = np.bincount(label[above], minlength=n)
    near = np.bincount(label[label >= 0], minlength=n)
    score = np.bincount(label[seen], minlength=n) * (in_box / np.maximum(near, 1)) ** 2
    score *= _outline_fit(projection.uv[label >= 0], label[label >= 0], n, box)
    winner = int(np.argmax(score))
    mine = above[label[above] == winner]
    free = mine[owner[mine] < 0]
    if len(free) < OWNED_SHARE * len(mine):
        return np.zeros(0, dtype=np.int64)  # an instance already (a few stray points aside)
    return free


def nearest_per_cell(uv: np.ndarray, depth: np.ndarray, cell_px: int = VOTE_CELL_PX) -> np.ndarray:
    """Indices of the points the camera sees: per image cell of `cell_px` pixels, the one
    nearest the camera (`uv` pixels, `depth` along the view)."""
    cell = np.floor(uv / cell_px).astype(np.int64)
    key = cell[:, 0] * (1 << 20) + cell[:, 1]
    order = np.lexsort((depth, key))
    first = np.ones(len(order), dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    return order[first]


def _outline_fit(uv: np.ndarray, label: np.ndarray, n: int, box: PixelBox) -> np.ndarray:
    """Per cluster: intersection over union of its points' box on the image with `box`."""
    lo, hi = label_extents(uv, label, n)
    inter = np.clip(np.minimum(hi, [box.u1, box.v1]) - np.maximum(lo, [box.u0, box.v0]), 0, None)
    inter_area = inter[:, 0] * inter[:, 1]
    own = np.clip(hi - lo, 0, None)
    union = own[:, 0] * own[:, 1] + box.area - inter_area
    return np.where(union > 0, inter_area / np.maximum(union, 1e-9), 0.0)


def checked_box(box: PixelBox, camera: Camera) -> PixelBox:
    """The box within the camera's image; ConfigError naming `box` when none of it is."""
    clipped = box.clipped(camera.width, camera.height)
    if clipped.area <= 0:
        raise ConfigError(
            "box",
            f"({box.u0:g}, {box.v0:g})-({box.u1:g}, {box.v1:g}) covers no pixel of camera "
            f"{camera.name}'s {camera.width} x {camera.height} image",
        )
    return clipped
