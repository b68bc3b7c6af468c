"""Ground truth of simulated points: read off the body and triangle each ray hit, plus the
phantom paper's pillar classes computed on the accumulated map.

Pillar classes (Nagy & Benedek, label set L): the map is cut into 0.2 m x 0.2 m pillars that
reach 3 m above the local ground (points higher up are ignored, as in the paper); the rule that
classes a pillar from its points is the shared one in `app.core.labels.classify_pillar_groups`.

Every point of a pillar carries the pillar's class (the paper's labelling); pipelines that keep
ground points under phantoms apply their own rule on top.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.labels import classify_pillar_groups
from app.geometry.pillars import PillarGrid
from app.simulate.scene import Scene

PILLAR_CELL = 0.2  # s_c, metres
PILLAR_HEIGHT = 3.0  # metres above the local ground


@dataclass
class PointTruth:
    semantic: np.ndarray  # (N,) uint16 SemanticKITTI id (static meaning)
    instance: np.ndarray  # (N,) uint32 body instance id, 0 for stuff
    moving: np.ndarray  # (N,) bool
    guardrail: np.ndarray  # (N,) int16 guardrail index, -1 elsewhere
    part: np.ndarray  # (N,) uint8 guardrail part (Part)
    halo: np.ndarray  # (N,) bool laser-bounce halo point

    def __len__(self) -> int:
        return len(self.semantic)

    def as_arrays(self) -> dict[str, np.ndarray]:
        return {
            "semantic": self.semantic,
            "instance": self.instance,
            "moving": self.moving,
            "guardrail": self.guardrail,
            "part": self.part,
            "halo": self.halo,
        }


MOVING_SPEED = 0.2  # m/s: a body moving slower than this when hit (e.g. waiting at a red light)
# counts as static at that moment, like SemanticKITTI's per-scan moving labels


class BodyTable:
    """Per-body lookup arrays so per-point truth is a handful of fancy-indexing operations."""

    def __init__(self, scene: Scene):
        bodies = scene.bodies
        self.motions = {i: b.motion for i, b in enumerate(bodies) if b.motion is not None}
        self.semantic = np.array([b.semantic for b in bodies], dtype=np.uint16)
        self.instance = np.array([b.instance for b in bodies], dtype=np.uint32)
        self.moving = np.array([b.moving for b in bodies], dtype=bool)
        self.guardrail = np.array([b.guardrail for b in bodies], dtype=np.int16)
        self.reflectivity = np.array([b.reflectivity for b in bodies], dtype=np.float64)
        counts = [len(b.mesh.triangles) for b in bodies]
        self.part_offset = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.parts = np.concatenate([b.mesh.part for b in bodies]).astype(np.uint8)

    def moving_at(self, body: np.ndarray, time: np.ndarray) -> np.ndarray:
        """Whether each point's body was moving (faster than MOVING_SPEED) when it was hit."""
        moving = self.moving[body]
        for index in np.unique(body[moving]):
            sel = body == index
            moving[sel] = self.motions[int(index)].speed(time[sel]) > MOVING_SPEED
        return moving

    def truth(
        self, body: np.ndarray, triangle: np.ndarray, halo: np.ndarray, time: np.ndarray
    ) -> PointTruth:
        return PointTruth(
            semantic=self.semantic[body],
            instance=self.instance[body],
            moving=self.moving_at(body, time),
            guardrail=self.guardrail[body],
            part=self.parts[self.part_offset[body] + triangle],
            halo=np.asarray(halo, dtype=bool),
        )


def pillar_classes(
    xyz: np.ndarray,
    semantic: np.ndarray,
    moving: np.ndarray,
    ground_height: np.ndarray,
    cell: float = PILLAR_CELL,
    height: float = PILLAR_HEIGHT,
    min_points: int = 3,
) -> np.ndarray:
    """(N,) uint8 pillar class of each point of an accumulated map (world xyz)."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.uint8)
    grid = PillarGrid.aligned(xyz[:, :2], cell)
    _, inverse, _ = grid.group(xyz[:, :2])
    in_column = xyz[:, 2] - ground_height <= height
    return classify_pillar_groups(inverse, semantic, moving, in_column, min_points)[inverse]
