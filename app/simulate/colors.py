"""The colours the simulated camera shades each SemanticKITTI class in (the ids themselves are
the shared vocabulary in `app.core.labels`)."""

from __future__ import annotations

from app.core.labels import Semantic

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
