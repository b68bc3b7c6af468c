"""Point labels from pillar labels, and the cleaned map.

Points above the local ground (by more than `ground_tolerance`) in the 3 m layer take their
pillar's label; points at ground level stay ground, so removing a phantom does not punch a hole
in the road under it (DESIGN.md: this lifts point-level phantom precision from 46-83 % to
97-100 % on SemanticKITTI); points outside the layer were ignored and get 0, as the command-line
contract says.
"""

from __future__ import annotations

import numpy as np

from app.core.labels import PillarClass
from app.pipelines.phantom.pillars import PillarMap


def point_labels(pm: PillarMap, pillar_labels: np.ndarray) -> np.ndarray:
    labels = np.zeros(len(pm.point_pillar), dtype=np.uint8)
    above = (pm.point_pillar >= 0) & (pm.height > pm.config.ground_tolerance)
    labels[above] = pillar_labels[pm.point_pillar[above]]
    return labels


def kept(labels: np.ndarray) -> np.ndarray:
    """Points of the cleaned map: everything but phantoms."""
    return labels != PillarClass.phantom
