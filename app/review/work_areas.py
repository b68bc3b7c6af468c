"""Work areas on the map: where along the drive each lies, which pillars it holds, and how far
its review has come (`app.store.work_areas` keeps the rows and the workflow).

A survey's drive is its frame poses (`survey_trajectory`); stations are metres along them
(`arc_length`). Areas are consecutive stretches of `length_m` metres (the last one shorter).
Every occupied pillar of the survey's map (`review/survey_map.py`: the viewer's cached map,
whose `cells` are the pillars with points) belongs to the area of the station nearest to it:
the drive resampled every `STEP_M` and searched with a KD-tree, the pillars a block at a time,
so memory stays at the pillar table plus a block. The pillars' stations are kept for the few
surveys asked about last (the map's cache name and the drive name them), so a coverage read is
the label queries and a few `bincount`s.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from sqlmodel import Session

from app.core.errors import ConflictError
from app.core.settings import Settings
from app.geometry.trajectory import arc_length
from app.review.survey_map import MapSource, SurveyMap, load_map
from app.store.models import User, WorkArea
from app.store.pillar_labels import STORE_GRID
from app.store.surveys import get_survey, survey_trajectory
from app.store.work_areas import (
    AreaPlan,
    check_length,
    frame_stations,
    human_cells,
    pending_clutter_by_frame,
    pending_model_stations,
    replace_areas,
    unreviewed_model_cells,
    unreviewed_slice_stations,
)

STEP_M = 0.5  # metres between the drive's samples a pillar's station is taken from
BLOCK = 1_000_000  # pillars per KD-tree query
_KEPT = 4  # surveys whose pillar stations stay in memory
_stations_cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
_cache_lock = threading.Lock()


@dataclass(frozen=True)
class Drive:
    """The survey's drive: sensor positions (world, float64) and their stations."""

    xyz: np.ndarray  # (M, 3)
    station: np.ndarray  # (M,) metres from the first frame

    @property
    def length(self) -> float:
        return float(self.station[-1]) if len(self.station) else 0.0

    def key(self) -> str:
        return hashlib.sha1(np.ascontiguousarray(self.xyz).tobytes()).hexdigest()[:16]

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) world xy every STEP_M metres (and the end), with their stations."""
        st = np.append(np.arange(0.0, self.length, STEP_M), self.length)
        xy = np.stack([np.interp(st, self.station, self.xyz[:, a]) for a in (0, 1)], axis=1)
        return xy, st

    def stations_of(self, xy: np.ndarray) -> np.ndarray:
        """Station of the drive sample nearest to each world xy, a block at a time."""
        samples, st = self.samples()
        tree = cKDTree(samples)
        out = np.empty(len(xy), dtype=np.float64)
        for start in range(0, len(xy), BLOCK):
            _, k = tree.query(xy[start : start + BLOCK], workers=-1)
            out[start : start + BLOCK] = st[k]
        return out


def survey_drive(session: Session, survey_id: int) -> Drive:
    xyz = survey_trajectory(session, survey_id)
    if not len(xyz):
        raise ConflictError(f"survey {survey_id} has no frame poses to cut its drive into areas")
    return Drive(xyz, arc_length(xyz))


def edges_of(length: float, length_m: float) -> np.ndarray:
    """Area boundaries 0, L, 2L, ..., length (one area for a drive of no length)."""
    n = max(1, int(np.ceil(length / length_m - 1e-9)))
    edges = np.minimum(np.arange(n + 1, dtype=np.float64) * length_m, length)
    edges[-1] = length
    return edges


def area_of(stations: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Index of the area each station falls in (before the first: 0; past the last: the last)."""
    n = len(edges) - 1
    return np.clip(np.searchsorted(edges, stations, side="right") - 1, 0, n - 1)


def open_map(session: Session, settings: Settings, survey_id: int) -> SurveyMap:
    """The survey's map as the viewer has it (built and cached when missing)."""
    source = MapSource.of(get_survey(session, survey_id))
    return load_map(source, settings.cache_dir, settings.viewer_overview_points)


def _cell_centres(survey_map: SurveyMap, start: int, stop: int) -> np.ndarray:
    ix, iy = STORE_GRID.decode(survey_map.cells[start:stop])
    return STORE_GRID.cell_center(ix, iy)


def pillar_stations(
    session: Session, settings: Settings, survey_id: int
) -> tuple[SurveyMap, Drive, np.ndarray]:
    """The map, the drive, and the station of each occupied pillar (`map.cells` order)."""
    drive = survey_drive(session, survey_id)
    survey_map = open_map(session, settings, survey_id)
    source = MapSource.of(get_survey(session, survey_id))
    key = (survey_id, source.cache_name(settings.viewer_overview_points), drive.key())
    with _cache_lock:
        if key in _stations_cache:
            _stations_cache.move_to_end(key)
            return survey_map, drive, _stations_cache[key]
    stations = np.empty(len(survey_map.cells), dtype=np.float64)
    for start in range(0, len(stations), BLOCK):
        stop = min(start + BLOCK, len(stations))
        stations[start:stop] = drive.stations_of(_cell_centres(survey_map, start, stop))
    with _cache_lock:
        _stations_cache[key] = stations
        while len(_stations_cache) > _KEPT:
            _stations_cache.popitem(last=False)
    return survey_map, drive, stations


# --- cutting ------------------------------------------------------------------------------


def plan_areas(
    session: Session, settings: Settings, survey_id: int, length_m: float
) -> list[AreaPlan]:
    """Areas of `length_m` metres of drive, each with the world box of its pillars (of its
    stretch of the drive where it holds none)."""
    length_m = check_length(length_m)
    survey_map, drive, stations = pillar_stations(session, settings, survey_id)
    edges = edges_of(drive.length, length_m)
    n = len(edges) - 1
    lo, hi = np.full((n, 2), np.inf), np.full((n, 2), -np.inf)
    half = STORE_GRID.cell_size / 2
    for start in range(0, len(stations), BLOCK):
        stop = min(start + BLOCK, len(stations))
        xy = _cell_centres(survey_map, start, stop)
        area = area_of(stations[start:stop], edges)
        np.minimum.at(lo, area, xy - half)
        np.maximum.at(hi, area, xy + half)
    plans = []
    for k in range(n):  # one area at a time: a loop over areas, not points
        if not np.isfinite(lo[k]).all():  # no pillar: the drive's stretch
            inside = (drive.station >= edges[k]) & (drive.station <= edges[k + 1])
            ends = np.stack(
                [np.interp(edges[k : k + 2], drive.station, drive.xyz[:, a]) for a in (0, 1)],
                axis=1,
            )
            xy = np.concatenate([ends, drive.xyz[inside, :2]])
            lo[k], hi[k] = xy.min(axis=0), xy.max(axis=0)
        box = (float(lo[k, 0]), float(lo[k, 1]), float(hi[k, 0]), float(hi[k, 1]))
        plans.append(AreaPlan(float(edges[k]), float(edges[k + 1]), box))
    return plans


def cut_areas(
    session: Session,
    settings: Settings,
    survey_id: int,
    length_m: float,
    user: User,
    replace: bool = False,
) -> list[WorkArea]:
    """Cut the survey's drive into areas and store them (`replace_areas`)."""
    plans = plan_areas(session, settings, survey_id, length_m)
    return replace_areas(session, survey_id, plans, user, length_m=length_m, replace=replace)


# --- coverage -----------------------------------------------------------------------------


@dataclass(frozen=True)
class AreaCoverage:
    """How far one area's review has come."""

    pillars: int  # pillars with points
    human_labelled: int  # of them, with a human label
    model_unreviewed: int  # of them, with a model pre-label and no human label
    clutter_pending: int  # clutter instances in its frames still pending a decision
    slices_unreviewed: int  # guardrail slices in its stretch no person labelled
    models_pending: int  # guardrail models (by their middle station) not reviewed

    @property
    def labelled_fraction(self) -> float:
        return self.human_labelled / self.pillars if self.pillars else 0.0


def coverage(
    session: Session, settings: Settings, survey_id: int, areas: Sequence[WorkArea]
) -> list[AreaCoverage]:
    """The coverage of each of the survey's `areas` (in drive order), all counted at once."""
    if not areas:
        return []
    n = len(areas)
    edges = np.append([a.station_start for a in areas], areas[-1].station_end).astype(float)
    survey_map, _, stations = pillar_stations(session, settings, survey_id)
    pillar_area = area_of(stations, edges)

    def per_area(indices: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        return np.bincount(indices, weights=weights, minlength=n)[:n].astype(np.int64)

    def labelled(cells: np.ndarray) -> np.ndarray:
        k, found = survey_map.cell_index(cells)
        return per_area(pillar_area[k[found]])

    frame_index, frame_station = frame_stations(session, survey_id)
    pending_frames, pending = pending_clutter_by_frame(session, survey_id)
    at = np.clip(np.searchsorted(frame_index, pending_frames), 0, max(len(frame_index) - 1, 0))
    clutter = per_area(area_of(frame_station[at], edges), pending) if len(pending) else None
    slices = unreviewed_slice_stations(session, survey_id)
    models = pending_model_stations(session, survey_id)
    models = models[np.isfinite(models)]
    columns = {
        "pillars": per_area(pillar_area),
        "human_labelled": labelled(human_cells(session, survey_id)),
        "model_unreviewed": labelled(unreviewed_model_cells(session, survey_id)),
        "clutter_pending": clutter if clutter is not None else np.zeros(n, np.int64),
        "slices_unreviewed": per_area(area_of(slices, edges)),
        "models_pending": per_area(area_of(models, edges)),
    }
    return [AreaCoverage(**{k: int(v[i]) for k, v in columns.items()}) for i in range(n)]
