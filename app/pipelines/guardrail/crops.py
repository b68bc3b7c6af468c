"""Cropped images of sliced segments (paper 3.2, Figs. 7-8).

Each slice's points are projected with the pinhole model into the camera images taken near it
(world -> sensor with the inverse frame pose, then `P @ T_cam_sensor`); the rectangle that holds
all projected points is cut out of the image. When several images contain *all* the slice's
points, the one with the largest rectangle wins (paper: "the image that contains all projected
points and has the largest rectangular area is selected").

Cost: frames near a slice are found with a KD-tree over the frame positions, and the slice's
centre is projected first; only the (frame, slice) pairs whose centre lands in the image (or
near it) get their points projected, each frame in one vectorised call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from app.geometry.projection import project
from app.io.survey import Survey
from app.pipelines.guardrail.slices import SliceSet


@dataclass
class Crop:
    """The chosen crop of one slice."""

    slice: int  # index into the SliceSet
    frame: int  # frame index in the survey
    frame_id: str
    camera: str
    box: tuple[int, int, int, int]  # (u0, v0, u1, v1) pixel rectangle cut (u1, v1 exclusive)
    points_box: tuple[float, float, float, float]  # tight (u_min, v_min, u_max, v_max)
    area: float  # tight rectangle area in px^2 (the selection criterion)
    image: np.ndarray | None  # (v1 - v0, u1 - u0, 3) uint8 RGB; None with load_images=False

    def resized(self, size: int = 224) -> np.ndarray:
        """The crop resized to size x size (the classifier's input), RGB uint8."""
        import cv2

        if self.image is None:
            raise ValueError("crop has no image (load_images=False)")
        return cv2.resize(self.image, (size, size), interpolation=cv2.INTER_AREA)


@dataclass
class _Candidate:
    slices: np.ndarray  # (C,) slice indices
    full: np.ndarray  # (C,) bool all points in image
    box: np.ndarray  # (C, 4) u_min, v_min, u_max, v_max


def _project_slices(
    xyz_world: np.ndarray,
    slice_set: SliceSet,
    slices: np.ndarray,
    T_cam_world: np.ndarray,
    P: np.ndarray,
    width: int,
    height: int,
    min_depth: float,
) -> _Candidate:
    """Project the points of `slices` into one image: all-in-image flag and tight box each."""
    starts = slice_set.offsets[slices]
    counts = slice_set.offsets[slices + 1] - starts
    # gather the point indices of the candidate slices, grouped, without a Python loop
    group_start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(int(counts.sum())) - np.repeat(group_start - starts, counts)
    pts = slice_set.indices[pos]
    proj = project(xyz_world[pts], P, T_cam_world, width, height, min_depth=min_depth)
    full = np.logical_and.reduceat(proj.in_image, group_start)
    u = np.where(proj.in_image, proj.uv[:, 0], np.nan)
    v = np.where(proj.in_image, proj.uv[:, 1], np.nan)
    with np.errstate(invalid="ignore"):
        box = np.stack(
            [
                np.fmin.reduceat(u, group_start),
                np.fmin.reduceat(v, group_start),
                np.fmax.reduceat(u, group_start),
                np.fmax.reduceat(v, group_start),
            ],
            axis=1,
        )
    return _Candidate(slices, full, box)


def _frame_pairs(
    positions: np.ndarray, frames: np.ndarray, centres: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """(frame, centre) pairs whose frame position lies within max_distance of the centre."""
    tree = cKDTree(positions[frames])
    near = tree.query_ball_point(centres, r=max_distance, workers=-1)
    counts = np.fromiter((len(x) for x in near), dtype=np.int64, count=len(near))
    if counts.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    flat = np.concatenate([np.asarray(x, dtype=np.int64) for x in near if len(x)])
    slices = np.repeat(np.arange(len(near)), counts)
    return frames[flat], slices


def slice_crops(
    survey: Survey,
    slice_set: SliceSet,
    xyz_world: np.ndarray,
    *,
    cameras: list[str] | None = None,
    max_distance: float = 40.0,
    margin: float = 0.1,
    min_margin_px: int = 4,
    min_depth: float = 1.0,
    centre_slack_px: float = 200.0,
    slices: np.ndarray | None = None,
    slice_time: np.ndarray | None = None,
    max_time_gap: float | None = None,
    load_images: bool = True,
) -> list[Crop]:
    """One crop per slice that some image shows whole (paper: largest such rectangle).

    - `cameras`: camera names to consider (default: all of `survey.cameras`).
    - `max_distance`: frames farther than this from the slice centre are not considered.
    - `margin`: extra border as a fraction of the rectangle's size, at least `min_margin_px`
      (the paper crops the bare rectangle; a thin wire of points needs some context).
    - `slices`: only these slice indices (default all). `slice_time` (K,) with `max_time_gap`:
      only images whose frame timestamp is that close (same clock as `Frame.timestamp`).
    Returns crops in slice order; slices that no image contains whole are left out.
    """
    xyz_world = np.asarray(xyz_world, dtype=np.float64)
    names = list(survey.cameras) if cameras is None else list(cameras)
    todo = np.arange(len(slice_set)) if slices is None else np.asarray(slices, dtype=np.int64)
    if len(todo) == 0 or not names or survey.is_map:
        return []
    poses = survey.poses()
    best_area = np.full(len(slice_set), -1.0)
    best: dict[int, tuple[int, str, np.ndarray]] = {}
    for name in names:
        cam = survey.cameras[name]
        frames = np.array([i for i, f in enumerate(survey.frames) if name in f.image_paths])
        if len(frames) == 0:
            continue
        pf, ps = _frame_pairs(poses[:, :3, 3], frames, slice_set.centre[todo], max_distance)
        ps = todo[ps]
        if max_time_gap is not None and slice_time is not None:
            stamps = np.array(
                [np.nan if f.timestamp is None else f.timestamp for f in survey.frames]
            )
            ok = np.abs(stamps[pf] - slice_time[ps]) <= max_time_gap
            pf, ps = pf[ok], ps[ok]
        # cheap pre-filter: the slice centre must land in (or near) the image
        T_cam_world = np.zeros((len(poses), 4, 4))
        T_cam_world[frames] = cam.T_cam_sensor @ np.linalg.inv(poses[frames])
        M = (cam.P @ T_cam_world)[pf]  # (C, 3, 4)
        c = slice_set.centre[ps]
        uvw = np.einsum("nij,nj->ni", M[:, :, :3], c) + M[:, :, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
            near = (uvw[:, 2] > min_depth) & (u > -centre_slack_px) & (v > -centre_slack_px)
            near &= (u < cam.width + centre_slack_px) & (v < cam.height + centre_slack_px)
        pf, ps = pf[near], ps[near]
        order = np.lexsort((ps, pf))
        pf, ps = pf[order], ps[order]
        bounds = np.flatnonzero(np.concatenate([[True], pf[1:] != pf[:-1]]))
        for a, b in zip(bounds, np.append(bounds[1:], len(pf)), strict=True):
            f = int(pf[a])
            cand = _project_slices(
                xyz_world,
                slice_set,
                ps[a:b],
                T_cam_world[f],
                cam.P,
                cam.width,
                cam.height,
                min_depth,
            )
            area = (cand.box[:, 2] - cand.box[:, 0]) * (cand.box[:, 3] - cand.box[:, 1])
            better = cand.full & (area > best_area[cand.slices])
            for k in np.flatnonzero(better):
                s = int(cand.slices[k])
                best_area[s] = area[k]
                best[s] = (f, name, cand.box[k])
    return _cut(survey, best, best_area, margin, min_margin_px, load_images)


def _cut(
    survey: Survey,
    best: dict[int, tuple[int, str, np.ndarray]],
    best_area: np.ndarray,
    margin: float,
    min_margin_px: int,
    load_images: bool,
) -> list[Crop]:
    """Cut the chosen rectangles, reading each needed image once."""
    by_image: dict[tuple[int, str], list[int]] = {}
    for s, (f, name, _) in best.items():
        by_image.setdefault((f, name), []).append(s)
    crops: list[Crop] = []
    for (f, name), slices in sorted(by_image.items()):
        cam = survey.cameras[name]
        frame = survey.frames[f]
        image = frame.image(name) if load_images else None
        h, w = (cam.height, cam.width) if image is None else image.shape[:2]
        for s in slices:
            box = best[s][2]
            pad_u = max(min_margin_px, margin * (box[2] - box[0]))
            pad_v = max(min_margin_px, margin * (box[3] - box[1]))
            u0 = int(max(0, np.floor(box[0] - pad_u)))
            v0 = int(max(0, np.floor(box[1] - pad_v)))
            u1 = int(min(w, np.ceil(box[2] + pad_u) + 1))
            v1 = int(min(h, np.ceil(box[3] + pad_v) + 1))
            crop = None if image is None else image[v0:v1, u0:u1].copy()
            crops.append(
                Crop(
                    slice=s,
                    frame=f,
                    frame_id=frame.frame_id,
                    camera=name,
                    box=(u0, v0, u1, v1),
                    points_box=tuple(float(x) for x in box),  # type: ignore[arg-type]
                    area=float(best_area[s]),
                    image=crop,
                )
            )
    crops.sort(key=lambda c: c.slice)
    return crops
