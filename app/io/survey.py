"""`Survey` and `Frame`: the one in-memory type every pipeline takes.

A survey is a sequence of frames. A frame knows where its points are on disk and loads them only
when asked, so a 500-frame drive never sits in memory. Points stay in the sensor frame; the frame's
4x4 `pose` maps them to world coordinates (float64). An already accumulated map (LAS, PLY, PCD) is a
survey with one frame whose id is `map`, identity pose and points already in world coordinates.

Reference labels (SemanticKITTI `.label`, LAS classification) ride along for evaluation only;
pipelines never read them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.core.errors import InputError

MAP_FRAME_ID = "map"


@dataclass
class PointCloud:
    """Points of one frame. `xyz` float64 (N, 3); the rest are per-point arrays of length N."""

    xyz: np.ndarray
    intensity: np.ndarray | None = None  # float32, sensor units (KITTI reflectance 0..1)
    time: np.ndarray | None = None  # float64 seconds, absolute (same clock as Frame.timestamp)
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # e.g. LAS classification

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.xyz)
        for name, values in [
            ("intensity", self.intensity),
            ("time", self.time),
            *self.extra.items(),
        ]:
            if values is not None and len(values) != n:
                raise ValueError(f"PointCloud.{name} has {len(values)} entries, xyz has {n}")

    def __len__(self) -> int:
        return len(self.xyz)

    def transformed(self, T: np.ndarray) -> PointCloud:
        """A copy with xyz mapped by the 4x4 transform T (float64)."""
        xyz = self.xyz @ T[:3, :3].T + T[:3, 3]
        return PointCloud(xyz, self.intensity, self.time, dict(self.extra))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera rigidly mounted with the scanner.

    Pixel coordinates of a sensor-frame point X: `[u*w, v*w, w] = P @ T_cam_sensor @ [X, 1]`.
    For KITTI, `P` is the rectified 3x4 projection (it may carry a stereo baseline in its last
    column) and `T_cam_sensor` maps velodyne to the rectified reference camera.
    """

    name: str  # e.g. "image_02" / "image_2"
    P: np.ndarray  # (3, 4) float64
    T_cam_sensor: np.ndarray  # (4, 4) float64
    width: int
    height: int
    calibration: str = ""  # the calibration entry P came from, e.g. "P2" or "P_rect_02"

    @property
    def K(self) -> np.ndarray:
        return self.P[:, :3]


@dataclass
class Frame:
    """One scan of the sensor. Points and images load lazily through the given callables."""

    index: int
    frame_id: str
    pose: np.ndarray  # (4, 4) float64 sensor -> world
    timestamp: float | None = None  # seconds
    point_count: int | None = None  # known without loading (file size, header)
    source_path: Path | None = None
    image_paths: dict[str, Path] = field(default_factory=dict)  # camera name -> image file
    _load_points: Callable[[], PointCloud] | None = field(default=None, repr=False)
    _load_reference: Callable[[], dict[str, np.ndarray]] | None = field(default=None, repr=False)
    # the points in pieces, file order: (index of the first, points), for files too large to
    # read whole (a LAS map); reference labels travel in `extra` under their kind's name
    _load_chunks: Callable[[], Iterator[tuple[int, PointCloud]]] | None = field(
        default=None, repr=False
    )

    def points(self) -> PointCloud:
        """Read this frame's points from disk (sensor frame, file order)."""
        if self._load_points is None:
            raise InputError(self.source_path, f"frame {self.frame_id} has no point source")
        return self._load_points()

    def world_points(self) -> PointCloud:
        return self.points().transformed(self.pose)

    def world_chunks(self) -> Iterator[tuple[int, PointCloud]]:
        """The frame's points in world coordinates, in pieces in file order (index of the
        first point, points): a chunk at a time where the reader can, else one piece."""
        if self._load_chunks is None:
            yield 0, self.world_points()
            return
        for start, cloud in self._load_chunks():
            yield start, cloud.transformed(self.pose)

    def reference_labels(self) -> dict[str, np.ndarray]:
        """Reference per-point labels for evaluation, e.g. {"semantic": ..., "instance": ...}."""
        return {} if self._load_reference is None else self._load_reference()

    def image(self, camera: str) -> np.ndarray:
        """The frame's RGB image (H, W, 3) uint8 of the named camera."""
        from app.io.images import read_rgb

        if camera not in self.image_paths:
            raise InputError(self.source_path, f"frame {self.frame_id} has no image for {camera}")
        return read_rgb(self.image_paths[camera])


@dataclass
class Survey:
    """A drive (sequence of posed frames) or an accumulated map (one frame `map`)."""

    name: str
    source: Path
    format: str
    frames: Sequence[Frame]
    cameras: dict[str, Camera] = field(default_factory=dict)
    poses_estimated: bool = False  # True when poses come from LiDAR odometry, not GNSS/INS
    reference_label_kinds: tuple[str, ...] = ()  # e.g. ("semantic", "instance"); empty = none
    trajectory: np.ndarray | None = None  # (M, 4, 4) sensor poses when known, for maps
    scanner: str | None = None  # e.g. "hdl64", "profile"; None when unknown
    # the scanner's parameters where the source records them (the simulator: beams, elevation
    # range, azimuth step, rate), e.g. to put a varied rotating scanner's points on its lattice
    scanner_params: dict[str, Any] | None = None
    # a map's first N points without reading the whole file (sensor-kind detection)
    sample_points: Callable[[int], PointCloud] | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    @property
    def is_map(self) -> bool:
        return len(self.frames) == 1 and self.frames[0].frame_id == MAP_FRAME_ID

    def poses(self) -> np.ndarray:
        """(F, 4, 4) sensor -> world pose per frame, or the map's trajectory when known."""
        if self.is_map and self.trajectory is not None:
            return self.trajectory
        return np.stack([f.pose for f in self.frames]) if self.frames else np.zeros((0, 4, 4))

    def frame(self, frame_id: str) -> Frame:
        for f in self.frames:
            if f.frame_id == frame_id:
                return f
        raise InputError(self.source, f"no frame with id {frame_id!r}")
