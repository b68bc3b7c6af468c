"""What a simulated street is made of: triangle meshes, bodies (static or moving) and the scene.

Every surface in the simulator is a triangle `Mesh` in the body's local frame; a `Body` gives it a
semantic class, an instance id and, when it moves, a `Motion` (pose as a function of time).
Static bodies have identity motion, their mesh is already in world coordinates. Ground truth of
every simulated point is read from the body (and triangle) its ray hit.

Semantic class ids follow SemanticKITTI (`app.core.labels`), so code that maps real
SemanticKITTI labels serves simulated surveys too; `moving` is a separate per-point flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Mesh:
    """Triangles in a local frame. `part` labels each triangle (guardrail parts, see classes)."""

    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int32
    part: np.ndarray | None = None  # (T,) uint8, 0 = no part

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int32).reshape(-1, 3)
        if self.part is None:
            self.part = np.zeros(len(self.triangles), dtype=np.uint8)
        self.part = np.asarray(self.part, dtype=np.uint8)
        if len(self.part) != len(self.triangles):
            raise ValueError("Mesh.part needs one entry per triangle")

    @staticmethod
    def merge(meshes: list[Mesh]) -> Mesh:
        """One mesh holding all triangles of `meshes` (parts kept)."""
        if not meshes:
            return Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32))
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate([m.triangles + o for m, o in zip(meshes, offsets, strict=True)]),
            np.concatenate([m.part for m in meshes]),
        )

    def transformed(self, R: np.ndarray, t: np.ndarray) -> Mesh:
        return Mesh(self.vertices @ np.asarray(R).T + t, self.triangles.copy(), self.part.copy())

    def bounding_radius(self) -> float:
        """Radius of a sphere about the local origin holding every vertex."""
        if not len(self.vertices):
            return 0.0
        return float(np.linalg.norm(self.vertices, axis=1).max())


@dataclass
class Motion:
    """Rigid motion of a moving body, sampled densely in time and interpolated linearly.

    At time t the body's local frame (x forward, y left, z up, origin at its ground centre) sits
    at `position(t)`, turned by `yaw(t)` about z and pitched nose-up by `pitch(t)` (slopes);
    before the first / after the last sample it stays where it was.
    """

    times: np.ndarray  # (K,) increasing seconds
    positions: np.ndarray  # (K, 3)
    yaws: np.ndarray  # (K,) radians, unwrapped
    pitches: np.ndarray | None = None  # (K,) radians, nose up positive; None = level

    def position(self, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return np.stack([np.interp(t, self.times, self.positions[:, k]) for k in range(3)], -1)

    def yaw(self, t: np.ndarray) -> np.ndarray:
        return np.interp(np.atleast_1d(np.asarray(t, dtype=np.float64)), self.times, self.yaws)

    def pitch(self, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return np.zeros_like(t) if self.pitches is None else np.interp(t, self.times, self.pitches)

    def rotations(self, t: np.ndarray) -> np.ndarray:
        """(N, 3, 3) local -> world rotations Rz(yaw) @ Ry(-pitch)."""
        yaw, pitch = self.yaw(t), self.pitch(t)
        cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
        R = np.empty((len(yaw), 3, 3))
        R[:, 0] = np.stack([cy * cp, -sy, -cy * sp], -1)
        R[:, 1] = np.stack([sy * cp, cy, -sy * sp], -1)
        R[:, 2] = np.stack([sp, np.zeros_like(sp), cp], -1)
        return R

    def poses(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) local -> world poses at times t."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = self.rotations(t)
        T[:, :3, 3] = self.position(t)
        return T

    def world_to_local(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per time: rotation (N, 3, 3) and translation (N, 3) mapping world -> local."""
        Rt = np.transpose(self.rotations(t), (0, 2, 1))
        return Rt, -np.einsum("nij,nj->ni", Rt, self.position(t))

    def local_to_world(self, t: float) -> np.ndarray:
        """4x4 pose of the body at one time."""
        return self.poses(np.array([t]))[0]

    def speed(self, t: np.ndarray) -> np.ndarray:
        """Ground speed (m/s) at times t, from the sampled path."""
        v = np.linalg.norm(np.diff(self.positions, axis=0), axis=1) / np.diff(self.times)
        mids = 0.5 * (self.times[1:] + self.times[:-1])
        return np.interp(np.asarray(t, dtype=np.float64), mids, v)


@dataclass
class Body:
    """One thing in the scene: its surface, what it is, and how it moves."""

    name: str  # e.g. "road", "building-3", "car-moving-2"
    mesh: Mesh
    semantic: int  # SemanticKITTI class id of the static object (car = 10 even when moving)
    instance: int  # > 0 for countable objects (cars, trees, poles, guardrails), 0 for stuff
    color: tuple[int, int, int]  # camera shading base colour (RGB)
    reflectivity: float = 0.3  # 0..1, drives the simulated intensity
    motion: Motion | None = None  # None: static, mesh in world coordinates
    guardrail: int = -1  # index into Scene.guardrails, -1 for anything else
    halo_margin: float = 0.0  # metres: laser-bounce "halo" around car bodies (clutter paper)
    shade: float = 1.0  # the camera's brightness factor: < 1 in deep shadow or dark paint

    @property
    def moving(self) -> bool:
        return self.motion is not None


@dataclass
class Scene:
    """A street: bodies, the survey vehicle's path, the ground and the guardrail models."""

    name: str
    seed: int
    bodies: list[Body]
    centerline: np.ndarray  # (M, 3) road centre polyline (world), z = road surface height
    vehicle_path: Motion  # survey vehicle: ground centre of the vehicle over time
    duration: float  # seconds the survey vehicle drives
    guardrails: list[dict] = field(default_factory=list)  # parametric models (JSON-ready)
    light_stop: tuple[float, float] | None = None  # (start, end) s of a red light, if any

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        """Height of the ground (road surface profile) under each xy: the road's height at the
        nearest centreline station; sidewalks add their curb, see `ground_offset`."""
        from scipy.spatial import cKDTree

        tree = cKDTree(self.centerline[:, :2])
        _, i = tree.query(np.asarray(xy)[:, :2], workers=-1)
        return self.centerline[i, 2]

    def static_bodies(self) -> list[int]:
        return [i for i, b in enumerate(self.bodies) if b.motion is None]

    def moving_bodies(self) -> list[int]:
        return [i for i, b in enumerate(self.bodies) if b.motion is not None]
