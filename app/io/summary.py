"""What `mmsclean info` prints: a survey's size, time span, trajectory and reference data."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from app.geometry.trajectory import total_length
from app.io.sensor_kind import detect_sensor_kind
from app.io.survey import Survey


@dataclass(frozen=True)
class SurveySummary:
    name: str
    format: str
    source: str
    kind: str  # "drive" or "map"
    frames: int
    points: int
    time_span_s: float | None
    trajectory_length_m: float | None
    poses: str  # "GNSS/INS", "estimated (LiDAR odometry)", "identity (map)", "given"
    cameras: list[str]
    reference_labels: list[str]
    sensor_kind: str = "unknown"  # rotating / profile / unknown (app.io.sensor_kind)
    sensor_reason: str = ""  # how it was told
    bounds_min: list[float] | None = None  # world xyz, only after a full check
    bounds_max: list[float] | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def summarize(survey: Survey) -> SurveySummary:
    frames = list(survey.frames)
    points = sum(f.point_count if f.point_count is not None else len(f.points()) for f in frames)
    stamps = [f.timestamp for f in frames if f.timestamp is not None]
    span = float(max(stamps) - min(stamps)) if len(stamps) >= 2 else None
    if survey.is_map:
        poses = "trajectory given" if survey.trajectory is not None else "none (accumulated map)"
    elif survey.poses_estimated:
        poses = "estimated (LiDAR odometry, KISS-ICP)"
    else:
        poses = "given (GNSS/INS or dataset poses)"
    trajectory = survey.poses()
    length = float(total_length(trajectory[:, :3, 3])) if len(trajectory) >= 2 else None
    sensor = detect_sensor_kind(survey)
    cameras = [
        f"{c.name} ({c.calibration + ', ' if c.calibration else ''}{c.width}x{c.height}, "
        f"images for {sum(c.name in f.image_paths for f in frames)}/{len(frames)} frames)"
        for c in survey.cameras.values()
    ]
    return SurveySummary(
        name=survey.name,
        format=survey.format,
        source=str(survey.source),
        kind="map" if survey.is_map else "drive",
        frames=len(frames),
        points=int(points),
        time_span_s=span,
        trajectory_length_m=None if length is None else round(length, 3),
        poses=poses,
        cameras=cameras,
        reference_labels=list(survey.reference_label_kinds),
        sensor_kind=sensor.kind.value,
        sensor_reason=sensor.reason,
    )


def check_frames(survey: Survey, summary: SurveySummary, progress=None) -> SurveySummary:
    """Read every frame (points and reference labels) so bad data fails now, not mid-pipeline;
    returns the summary with the exact point count and the world bounding box."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    points = 0
    for frame in survey.frames:
        cloud = frame.world_points()
        frame.reference_labels()
        points += len(cloud)
        if len(cloud):
            lo = np.minimum(lo, cloud.xyz.min(axis=0))
            hi = np.maximum(hi, cloud.xyz.max(axis=0))
        if progress is not None:
            progress()
    bounds = points > 0
    return replace(
        summary,
        points=points,
        bounds_min=[round(float(v), 3) for v in lo] if bounds else None,
        bounds_max=[round(float(v), 3) for v in hi] if bounds else None,
    )


def format_count(n: int) -> str:
    return f"{n:,}" if n < 1e6 else f"{n:,} ({n / 1e6:.2f}M)"


def summary_rows(s: SurveySummary) -> list[tuple[str, str]]:
    rows = [
        ("survey", s.name),
        ("format", f"{s.format} ({s.kind})"),
        ("source", s.source),
        ("frames", str(s.frames)),
        ("points", format_count(s.points)),
        ("time span", "unknown" if s.time_span_s is None else f"{s.time_span_s:.3f} s"),
        (
            "trajectory length",
            "unknown" if s.trajectory_length_m is None else f"{s.trajectory_length_m:.2f} m",
        ),
        ("poses", s.poses),
        ("sensor", f"{s.sensor_kind} ({s.sensor_reason})" if s.sensor_reason else s.sensor_kind),
        ("cameras", ", ".join(s.cameras) if s.cameras else "none"),
        ("reference labels", ", ".join(s.reference_labels) if s.reference_labels else "none"),
    ]
    if s.bounds_min is not None and s.bounds_max is not None:
        rows.append(("world bounds", f"{s.bounds_min} .. {s.bounds_max}"))
    return rows
