"""The label vocabulary every layer shares: SemanticKITTI class ids, guardrail parts, the per-point
label values the three pipelines write (clutter, phantom = pillar classes, guardrail) and the rule
that derives a pillar's reference class from its points.

It lives at the bottom (core) so the simulator, the pipelines, the metrics and the store read one
definition; pure numpy, nothing else of `app`.

Pillar rule (Nagy & Benedek, label set L): within a pillar the non-ground points decide:

- fewer than `min_points` non-ground points: ground;
- moving points are the majority of the non-ground points: phantom (moving vehicles,
  cyclists, pedestrians, also a moving tram: the paper's phantoms are "effects of moving
  vehicles and pedestrians");
- otherwise the static non-ground points vote: high object (facades, trunks, poles, signs,
  parked trucks / buses / trams) against short object (parked cars and vans, guardrails,
  street furniture, standing people); ties go to high object.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Semantic(IntEnum):
    """SemanticKITTI class ids (static meaning; motion is a separate flag)."""

    UNLABELED = 0
    CAR = 10
    BICYCLE = 11
    BUS = 13
    MOTORCYCLE = 15
    ON_RAILS = 16  # tram
    TRUCK = 18
    OTHER_VEHICLE = 20  # van
    PERSON = 30
    BICYCLIST = 31
    MOTORCYCLIST = 32
    ROAD = 40
    PARKING = 44
    SIDEWALK = 48  # sidewalks and curbs
    OTHER_GROUND = 49
    BUILDING = 50
    FENCE = 51  # guardrails (SemanticKITTI labels highway guardrails fence)
    OTHER_STRUCTURE = 52
    LANE_MARKING = 60
    VEGETATION = 70  # tree crowns
    TRUNK = 71
    TERRAIN = 72
    POLE = 80
    TRAFFIC_SIGN = 81
    OTHER_OBJECT = 99


FENCE = int(Semantic.FENCE)  # SemanticKITTI labels highway guardrails "fence"

# SemanticKITTI adds 242 to the id of a moving object: car 10 -> moving-car 252, etc.; a moving
# bicycle is its bicyclist (253), a moving motorcycle its motorcyclist (255)
MOVING_OFFSET = {
    10: 252, 31: 253, 30: 254, 16: 256, 13: 257, 18: 258, 20: 259, 11: 253, 15: 255, 32: 255
}  # fmt: skip
# SemanticKITTI moving class -> its static class
MOVING_TO_STATIC = {252: 10, 253: 31, 254: 30, 255: 32, 256: 16, 257: 13, 258: 18, 259: 20}
MOVING_IDS = np.arange(252, 260)
# every movable class, parked or moving (cars, bicycles, buses, motorcycles, trams, trucks, other
# vehicles, persons, bicyclists, motorcyclists: 10-32 and 252-259)
MOVABLE_IDS = np.array([10, 11, 13, 15, 16, 18, 20, 30, 31, 32, *MOVING_IDS])
UNSCORED_IDS = np.array([0, 1])  # unlabelled and outlier points have no reference class

GROUND_CLASSES = frozenset(
    {Semantic.ROAD, Semantic.PARKING, Semantic.SIDEWALK, Semantic.OTHER_GROUND,
     Semantic.LANE_MARKING, Semantic.TERRAIN}
)  # fmt: skip
# static non-ground objects the phantom paper calls "high objects"; everything else is "short"
HIGH_CLASSES = frozenset(
    {Semantic.BUILDING, Semantic.OTHER_STRUCTURE, Semantic.VEGETATION, Semantic.TRUNK,
     Semantic.POLE, Semantic.TRAFFIC_SIGN, Semantic.BUS, Semantic.ON_RAILS, Semantic.TRUCK}
)  # fmt: skip
# the classes the clutter paper removes, as SemanticKITTI ids
CLUTTER_SEMANTIC = frozenset(
    {Semantic.CAR, Semantic.BICYCLE, Semantic.BUS, Semantic.ON_RAILS, Semantic.TRUCK,
     Semantic.OTHER_VEHICLE, Semantic.PERSON, Semantic.BICYCLIST}
)  # fmt: skip

# the clutter pipeline's object classes (its camera classes, `segmenter.CLUTTER_CLASSES`, and
# `moved-track`: an object nobody classed that moves at a vehicle's speed) as SemanticKITTI's
# static classes; a Cityscapes "rider" is taken for a bicyclist
CLUTTER_CLASS_SEMANTIC: dict[str, Semantic] = {
    "person": Semantic.PERSON,
    "rider": Semantic.BICYCLIST,
    "car": Semantic.CAR,
    "truck": Semantic.TRUCK,
    "bus": Semantic.BUS,
    "train": Semantic.ON_RAILS,
    "motorcycle": Semantic.MOTORCYCLE,
    "bicycle": Semantic.BICYCLE,
    "moved-track": Semantic.OTHER_VEHICLE,
}


def semantic_name(label: int) -> str:
    """SemanticKITTI's name of a class id known here ("moving-car" for 252); "" otherwise."""
    if label in MOVING_TO_STATIC:
        return "moving-" + semantic_name(MOVING_TO_STATIC[label])
    try:
        return Semantic(label).name.lower().replace("_", "-")
    except ValueError:
        return ""


class Part(IntEnum):
    """Guardrail part of a point (0 for everything that is not a guardrail)."""

    NONE = 0
    PIPE = 1
    BEAM = 2
    POLE = 3


class PillarClass(IntEnum):
    """The phantom paper's four pillar classes (label set L); the same numbers as the phantom
    `labels/*.npy`, the stored pillar labels and the API (which names them by `.name`)."""

    ground = 0
    high_object = 1
    short_object = 2
    phantom = 3


PILLAR_CLASS_NAMES = tuple(c.name.replace("_", " ") for c in PillarClass)  # for people


class ClutterLabel(IntEnum):
    """Per-point label of a clutter run (`labels/*.npy`, the command-line contract)."""

    KEPT = 0
    REMOVED = 1


class GuardrailLabel(IntEnum):
    """Per-point label of a guardrail run (`labels/*.npy`, the command-line contract)."""

    OTHER = 0
    GUARDRAIL = 1


def classify_pillar_groups(
    group: np.ndarray,
    semantic: np.ndarray,
    moving: np.ndarray,
    in_column: np.ndarray,
    min_points: int = 3,
) -> np.ndarray:
    """The pillar rule (module docstring) for points grouped into pillars: (G,) uint8 class of
    each group id 0..G-1 from its points' static SemanticKITTI class and moving flag; only
    points with `in_column` count."""
    non_ground = in_column & ~np.isin(semantic, list(GROUND_CLASSES))
    n = int(group.max()) + 1 if len(group) else 0
    count = np.bincount(group, weights=non_ground, minlength=n)
    moving_count = np.bincount(group, weights=non_ground & moving, minlength=n)
    static = non_ground & ~moving
    high = np.bincount(group, weights=static & np.isin(semantic, list(HIGH_CLASSES)), minlength=n)
    short = count - moving_count - high
    classes = np.full(n, PillarClass.ground, dtype=np.uint8)
    occupied = count >= min_points
    classes[occupied & (high >= short)] = PillarClass.high_object
    classes[occupied & (high < short)] = PillarClass.short_object
    classes[occupied & (2 * moving_count > count)] = PillarClass.phantom
    return classes
