"""What `mmsclean info` prints: a survey's size, time span, trajectory and reference data."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from app.geometry.trajectory import total_length
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
    cameras = [
        f"{c.name} ({c.width}x{c.height}, images for "
        f"{sum(c.name in f.image_paths for f in frames)}/{len(frames)} frames)"
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
    )


def format_count(n: int) -> str:
    return f"{n:,}" if n < 1e6 else f"{n:,} ({n / 1e6:.2f}M)"


def summary_rows(s: SurveySummary) -> list[tuple[str, str]]:
    return [
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
        ("cameras", ", ".join(s.cameras) if s.cameras else "none"),
        ("reference labels", ", ".join(s.reference_labels) if s.reference_labels else "none"),
    ]
