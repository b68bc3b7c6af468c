"""Tell the scanner kind (rotating / profile) of a survey from its readers or its point times.

Readers of sensor formats know their scanner (KITTI raw and SemanticKITTI: HDL-64E; the
simulator writes its scanner into `simulation.json`). A LAS / PLY / PCD map does not say, but
its point times do where it has them: the *revisit period*, the time between two passes of the
scanner over the same 0.5 m voxel, is the scanner's line period for a profile scanner (it sweeps
a fixed plane 50-500 times a second, so the plane crosses a voxel again 2-20 ms later) and its
revolution period for a rotating one (5-20 Hz: 50-200 ms), whatever the vehicle's speed, even
standing still. Passes are told apart by gaps over 0.5 ms (inside one pass the points of a voxel
come microseconds apart). The median revisit period of a sample of the map decides: under 25 ms
profile, 40 ms to 1 s rotating; anything else, no times, or too few revisited voxels is
`unknown`, which the operator declares at import.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.sensors import SensorKind, kind_of_scanner
from app.io.survey import Survey

VOXEL_M = 0.5
PASS_GAP_S = 5e-4  # gaps within one pass of the scanner are microseconds
PROFILE_MAX_S = 0.025  # line periods: 2-20 ms (50-500 lines / s)
ROTATING_RANGE_S = (0.040, 1.0)  # revolution periods: 50-200 ms (5-20 Hz)
MIN_REVISITS = 1_000  # revisited voxels needed for a verdict
SAMPLE_POINTS = 2_000_000  # points a detection reads (the first ones of the file)


@dataclass(frozen=True)
class SensorDetection:
    kind: SensorKind
    reason: str  # one line for `mmsclean info` and the import's audit event


def revisit_periods(xyz: np.ndarray, time: np.ndarray) -> np.ndarray:
    """Per revisit of a voxel: the seconds since the previous pass over it."""
    cells = np.floor(np.asarray(xyz, dtype=np.float64) / VOXEL_M).astype(np.int64)
    order = np.lexsort((time, cells[:, 2], cells[:, 1], cells[:, 0]))
    cells, t = cells[order], np.asarray(time, dtype=np.float64)[order]
    same_voxel = np.all(cells[1:] == cells[:-1], axis=1)
    gaps = np.diff(t)[same_voxel]
    return gaps[gaps > PASS_GAP_S]


def detect_from_times(xyz: np.ndarray, time: np.ndarray | None) -> SensorDetection:
    """The kind told by the revisit period of these points (see the module docstring)."""
    if time is None or len(time) == 0:
        return SensorDetection(SensorKind.UNKNOWN, "the points carry no time")
    finite = np.isfinite(time)
    if not finite.all():
        xyz, time = xyz[finite], time[finite]
    if not len(time) or np.ptp(time) == 0:
        return SensorDetection(SensorKind.UNKNOWN, "every point has the same time (none recorded)")
    periods = revisit_periods(xyz, time)
    if len(periods) < MIN_REVISITS:
        return SensorDetection(
            SensorKind.UNKNOWN,
            f"only {len(periods)} revisited voxels in the point times (need {MIN_REVISITS})",
        )
    median = float(np.median(periods))
    found = f"median revisit period {median * 1000:.1f} ms over {len(periods):,} revisits"
    if median < PROFILE_MAX_S:
        return SensorDetection(SensorKind.PROFILE, f"{found}: a profile scanner's line period")
    if ROTATING_RANGE_S[0] <= median <= ROTATING_RANGE_S[1]:
        return SensorDetection(SensorKind.ROTATING, f"{found}: a rotating scanner's revolution")
    return SensorDetection(SensorKind.UNKNOWN, f"{found}: neither a line nor a revolution period")


def detect_sensor_kind(survey: Survey) -> SensorDetection:
    """The survey's kind: its reader's scanner where known, else its map's point times."""
    kind = kind_of_scanner(survey.scanner)
    if kind is not SensorKind.UNKNOWN:
        return SensorDetection(kind, f"{survey.format} reader: scanner {survey.scanner}")
    if not survey.is_map:
        return SensorDetection(SensorKind.UNKNOWN, f"{survey.format} reader names no scanner")
    if survey.sample_points is None:
        return SensorDetection(SensorKind.UNKNOWN, f"{survey.format} map: no point sample")
    sample = survey.sample_points(SAMPLE_POINTS)
    return detect_from_times(sample.xyz, sample.time)
