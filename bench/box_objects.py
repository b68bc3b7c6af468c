"""A missed object from a 2D box on the camera image, on real SemanticKITTI 04 / 05 / 08 (all ten
frames each): every labelled movable object in the camera's view (>= MIN_POINTS points on the
image) is boxed as an annotator would box it (its labelled points' extent on the image, MARGIN px
wider) with no instance in the frame, and `app.review.box_objects.object_in_box` answers. Its
points against the object's own points in the box: precision, recall, and the share of objects
taken well (point IoU >= 0.8). The baseline is what a box alone gives (every point above the
ground in the box, as a frustum selection would), measured in the same run; the time is the
server's per box (the viewer's clustering and vote, not the store write).

The rule's parts (the visible-surface vote, the containment, the outline fit) were chosen while
looking at frames 000000 and 000005 of these sequences: this is not a held-out figure.

Usage: MMSCLEAN_REAL_DATA=../shared/data python -m bench.box_objects [--no-record]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from app.geometry.projection import project
from app.io import open_survey
from app.pipelines.clutter.clusters import frame_clusters
from app.pipelines.clutter.config import ClutterConfig
from app.review.box_objects import VOTE_CELL_PX, PixelBox, nearest_per_cell, object_in_box
from bench.common import append_results, markdown_table

SEQUENCES = ("04", "05", "08")
MOVABLE = np.r_[10:33, 252:260]  # SemanticKITTI's vehicles, persons, riders, moving ones
MIN_POINTS = 20  # an object with fewer points on the image is not one an annotator boxes
MARGIN = 6.0  # pixels round the object's extent, as a hand-drawn box leaves
GOOD_IOU = 0.8
GROUND = (40, 44, 48, 49, 60, 72)  # road, parking, sidewalk, other ground, lane marking, terrain
SEEN_SHARE = 0.5  # an object the camera sees: its own point is the nearest in this share of
# its cells on the image (ground aside); the others are hidden behind another object


def seen_share(proj, labels: np.ndarray, mine: np.ndarray) -> float:
    """Of the image cells (VOTE_CELL_PX) the object covers, the share where its point is the
    nearest non-ground point: how much of it an annotator sees."""
    solid = proj.in_image & ~np.isin(labels & 0xFFFF, GROUND)
    idx = np.flatnonzero(solid)
    cell = np.floor(proj.uv[idx] / VOTE_CELL_PX).astype(np.int64)
    key = cell[:, 0] * (1 << 20) + cell[:, 1]
    own = np.unique(key[mine[idx]])
    near = np.isin(key, own)
    idx = idx[near]
    return float(mine[idx[nearest_per_cell(proj.uv[idx], proj.depth[idx])]].mean())


def box_baseline(xyz: np.ndarray, proj, box: PixelBox, config: ClutterConfig) -> np.ndarray:
    """Every point above the ground inside the box (no vote)."""
    inside = proj.in_image & box.holds(proj.uv)
    clusters = frame_clusters(
        xyz, config.cluster_voxel, config.ground_cell, config.ground_tolerance,
        config.max_range, subset=inside,
    )  # fmt: skip
    return np.flatnonzero(clusters.label >= 0)


def score(got: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    tp = len(np.intersect1d(got, truth))
    union = len(got) + len(truth) - tp
    return tp / max(len(got), 1), tp / max(len(truth), 1), tp / max(union, 1)


def measure(root: Path) -> list[list[str]]:
    config = ClutterConfig()
    rows, every = [], {"box": [], "baseline": [], "ms": [], "seen": []}
    for seq in SEQUENCES:
        source = root / "semantickitti" / "sequences" / seq
        survey = open_survey(source, "semantickitti")
        camera = next(iter(survey.cameras.values()))
        found = {"box": [], "baseline": [], "ms": [], "seen": []}
        for frame in survey.frames:
            xyz = frame.points().xyz
            labels = np.fromfile(source / "labels" / f"{frame.frame_id}.label", dtype="<u4")
            proj = project(xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
            movable = np.isin(labels & 0xFFFF, MOVABLE) & proj.in_image
            ids, counts = np.unique(labels[movable], return_counts=True)
            owner = np.full(len(xyz), -1, np.int32)
            for label in ids[counts >= MIN_POINTS]:
                mine = movable & (labels == label)
                uv = proj.uv[mine]
                box = PixelBox(*(uv.min(axis=0) - MARGIN), *(uv.max(axis=0) + MARGIN))
                box = box.clipped(camera.width, camera.height)
                truth = np.flatnonzero(mine)
                start = time.perf_counter()
                got = object_in_box(xyz, proj, owner, box, config)
                found["ms"].append(1000 * (time.perf_counter() - start))
                found["box"].append(score(got, truth))
                found["baseline"].append(score(box_baseline(xyz, proj, box, config), truth))
                found["seen"].append(seen_share(proj, labels, mine))
        for key in every:
            every[key] += found[key]
        rows += table_rows(seq, found)
    return rows + table_rows("all", every)


def table_rows(name: str, found: dict[str, list]) -> list[list[str]]:
    rows = []
    seen = np.asarray(found["seen"]) >= SEEN_SHARE
    for part, keep in (("seen", seen), ("hidden", ~seen)):
        if not keep.any():
            continue
        for key, what in (("baseline", "box alone (above ground)"), ("box", "object_in_box")):
            s = np.asarray(found[key]).reshape(-1, 3)[keep]
            ms = np.asarray(found["ms"])[keep]
            rows.append(row(f"{name} {part}", what, s, ms, key == "box"))
    return rows


def row(name: str, what: str, s: np.ndarray, ms: np.ndarray, timed: bool) -> list[str]:
    return [
            name, what, str(len(s)), f"{100 * s[:, 0].mean():.1f}", f"{100 * s[:, 1].mean():.1f}",
            f"{100 * np.median(s[:, 2]):.1f}", f"{100 * (s[:, 2] >= GOOD_IOU).mean():.1f}",
            f"{np.percentile(ms, 50):.0f} / {np.percentile(ms, 90):.0f}" if timed else "",
        ]  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-record", action="store_true", help="print, do not append")
    args = parser.parse_args()
    value = os.environ.get("MMSCLEAN_REAL_DATA")
    if not value:
        print("MMSCLEAN_REAL_DATA is not set: the real SemanticKITTI sample is needed")
        return 2
    rows = measure(Path(value))
    header = ["sequence", "selection", "objects", "precision %", "recall %", "median IoU %",
              f"IoU >= {GOOD_IOU}: %", "ms p50 / p90"]  # fmt: skip
    table = markdown_table(header, rows)
    print(table)
    if not args.no_record:
        append_results(
            "Clutter review: a missed object from a 2D box on the camera image (real)",
            "MMSCLEAN_REAL_DATA=../shared/data .venv/bin/python -m bench.box_objects",
            table,
            f"Every labelled movable object with >= {MIN_POINTS} points on the image of 10 "
            f"frames per sequence, boxed by its labelled extent + {MARGIN:g} px, no instance in "
            "the frame. Precision / recall: mean over objects of the points taken against the "
            "object's points. Not held out: the rule was shaped on frames 000000 and 000005.",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
