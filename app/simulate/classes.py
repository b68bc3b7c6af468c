"""Class ids of simulated points (SemanticKITTI's), guardrail parts and the phantom paper's
pillar classes, with the colours the simulated camera shades them in."""

from __future__ import annotations

from enum import IntEnum


class Semantic(IntEnum):
    """SemanticKITTI class ids (static meaning; motion is a separate flag)."""

    UNLABELED = 0
    CAR = 10
    BICYCLE = 11
    BUS = 13
    ON_RAILS = 16  # tram
    TRUCK = 18
    OTHER_VEHICLE = 20  # van
    PERSON = 30
    BICYCLIST = 31
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


# SemanticKITTI adds 242 to the id of a moving object: car 10 -> moving-car 252, etc.
MOVING_OFFSET = {10: 252, 31: 253, 30: 254, 16: 256, 13: 257, 18: 258, 20: 259, 11: 253}

GROUND_CLASSES = frozenset(
    {Semantic.ROAD, Semantic.PARKING, Semantic.SIDEWALK, Semantic.OTHER_GROUND,
     Semantic.LANE_MARKING, Semantic.TERRAIN}
)  # fmt: skip
# static non-ground objects the phantom paper calls "high objects"; everything else is "short"
HIGH_CLASSES = frozenset(
    {Semantic.BUILDING, Semantic.OTHER_STRUCTURE, Semantic.VEGETATION, Semantic.TRUNK,
     Semantic.POLE, Semantic.TRAFFIC_SIGN, Semantic.BUS, Semantic.ON_RAILS, Semantic.TRUCK}
)  # fmt: skip
CLUTTER_CLASSES = frozenset(
    {Semantic.CAR, Semantic.BICYCLE, Semantic.BUS, Semantic.ON_RAILS, Semantic.TRUCK,
     Semantic.OTHER_VEHICLE, Semantic.PERSON, Semantic.BICYCLIST}
)  # fmt: skip


class Part(IntEnum):
    """Guardrail part of a point (0 for everything that is not a guardrail)."""

    NONE = 0
    PIPE = 1
    BEAM = 2
    POLE = 3


class PillarClass(IntEnum):
    """The phantom paper's four pillar classes (label set L)."""

    GROUND = 0
    HIGH_OBJECT = 1
    SHORT_OBJECT = 2
    PHANTOM = 3


COLORS: dict[int, tuple[int, int, int]] = {
    Semantic.UNLABELED: (0, 0, 0),
    Semantic.CAR: (200, 40, 40),
    Semantic.BICYCLE: (230, 120, 20),
    Semantic.BUS: (230, 200, 30),
    Semantic.ON_RAILS: (240, 160, 40),
    Semantic.TRUCK: (150, 30, 90),
    Semantic.OTHER_VEHICLE: (170, 70, 160),
    Semantic.PERSON: (240, 80, 160),
    Semantic.BICYCLIST: (250, 50, 100),
    Semantic.ROAD: (90, 90, 95),
    Semantic.PARKING: (110, 100, 110),
    Semantic.SIDEWALK: (170, 160, 150),
    Semantic.OTHER_GROUND: (120, 110, 90),
    Semantic.BUILDING: (200, 170, 130),
    Semantic.FENCE: (210, 210, 220),
    Semantic.OTHER_STRUCTURE: (140, 130, 120),
    Semantic.LANE_MARKING: (245, 245, 245),
    Semantic.VEGETATION: (60, 150, 50),
    Semantic.TRUNK: (110, 70, 40),
    Semantic.TERRAIN: (130, 170, 80),
    Semantic.POLE: (150, 150, 160),
    Semantic.TRAFFIC_SIGN: (40, 80, 220),
}
SKY_COLOR = (170, 200, 235)
