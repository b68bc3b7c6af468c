"""ASPRS LAS classification codes and how mmsclean's labels map onto them.

The codes are those of the LAS 1.4 specification (R15, table 17, point formats 6-10). Codes 64-255
are "user definable"; mmsclean uses two of them, listed below, for things ASPRS has no code for.

Writers (the cleaned map, exports) store mmsclean's own per-point labels in the `mmsclean_label`
extra dimension; the ASPRS `classification` they write next to it is only a courtesy to other LAS
tools and follows the mappings here.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from app.core.labels import ClutterLabel, GuardrailLabel, PillarClass, Semantic


class AsprsClass(IntEnum):
    """ASPRS standard point classes (LAS 1.4, point formats 6-10)."""

    CREATED_NEVER_CLASSIFIED = 0
    UNCLASSIFIED = 1
    GROUND = 2
    LOW_VEGETATION = 3
    MEDIUM_VEGETATION = 4
    HIGH_VEGETATION = 5
    BUILDING = 6
    LOW_POINT_NOISE = 7
    WATER = 9
    RAIL = 10
    ROAD_SURFACE = 11
    WIRE_GUARD_SHIELD = 13
    WIRE_CONDUCTOR = 14
    TRANSMISSION_TOWER = 15
    WIRE_STRUCTURE_CONNECTOR = 16
    BRIDGE_DECK = 17
    HIGH_NOISE = 18
    OVERHEAD_STRUCTURE = 19
    IGNORED_GROUND = 20
    # user-definable range (64-255), mmsclean's own classes:
    GUARDRAIL = 64
    REMOVED_CLUTTER = 65


USER_DEFINED_MIN = 64
"""Codes 64..255 are user definable in LAS 1.4."""

GUARDRAIL_ASPRS = int(AsprsClass.GUARDRAIL)
"""Guardrail points (guardrail pipeline label 1). ASPRS has no class for road furniture, so a
user-defined code; 64 is the first one."""

REMOVED_CLUTTER_ASPRS = int(AsprsClass.REMOVED_CLUTTER)
"""Points of moving objects / clutter that a pipeline removed from the map: clutter pipeline label 1
and phantom pipeline label 3. They are real laser returns from objects that do not belong in a
static map, not sensor noise, so they get their own user-defined code instead of 7/18."""

PHANTOM_LABEL_TO_ASPRS: dict[int, int] = {
    PillarClass.ground: int(AsprsClass.GROUND),
    PillarClass.high_object: int(AsprsClass.UNCLASSIFIED),  # trees, poles, walls, not only houses
    PillarClass.short_object: int(AsprsClass.UNCLASSIFIED),  # kerbs, bins, parked things
    PillarClass.phantom: REMOVED_CLUTTER_ASPRS,  # trace of a moving object
}
"""Phantom pipeline label (0 ground, 1 high object, 2 short object, 3 phantom) -> ASPRS code.

Why: "high object" mixes buildings, vegetation and poles, so 6 (building) would be wrong for most of
it; 1 (unclassified) is the honest code. Phantoms are returns from moving vehicles and people; the
ASPRS noise classes (7 low point, 18 high noise) mean spurious sensor returns below/above the
surface, which they are not, and reusing them would hide real noise. They share the user-defined
"removed clutter" code with the clutter pipeline's removed points, so one class filter drops every
moving-object point whichever pipeline found it.
"""

CLUTTER_LABEL_TO_ASPRS: dict[int, int] = {
    ClutterLabel.KEPT: int(AsprsClass.UNCLASSIFIED),
    ClutterLabel.REMOVED: REMOVED_CLUTTER_ASPRS,
}
"""Clutter pipeline label (0 kept, 1 removed) -> ASPRS code."""

GUARDRAIL_LABEL_TO_ASPRS: dict[int, int] = {
    GuardrailLabel.OTHER: int(AsprsClass.UNCLASSIFIED),
    GuardrailLabel.GUARDRAIL: GUARDRAIL_ASPRS,
}
"""Guardrail pipeline label (0 other, 1 guardrail) -> ASPRS code."""


def to_asprs(labels: np.ndarray, mapping: dict[int, int], default: int = 1) -> np.ndarray:
    """Map per-point pipeline labels (uint8) to ASPRS codes (uint8) with a lookup table.

    Labels not in `mapping` get `default` (1, unclassified).
    """
    labels = np.asarray(labels)
    if labels.size and (labels.min() < 0 or labels.max() > 255):
        raise ValueError(f"labels must lie in 0..255, got {labels.min()}..{labels.max()}")
    table = np.full(256, default, dtype=np.uint8)
    for label, code in mapping.items():
        table[label] = code
    return table[labels.astype(np.intp)]


SEMANTICKITTI_TO_ASPRS: dict[int, int] = {
    Semantic.ROAD: int(AsprsClass.ROAD_SURFACE),
    Semantic.PARKING: int(AsprsClass.ROAD_SURFACE),
    Semantic.LANE_MARKING: int(AsprsClass.ROAD_SURFACE),
    Semantic.SIDEWALK: int(AsprsClass.GROUND),
    Semantic.OTHER_GROUND: int(AsprsClass.GROUND),
    Semantic.TERRAIN: int(AsprsClass.GROUND),
    Semantic.BUILDING: int(AsprsClass.BUILDING),
    Semantic.VEGETATION: int(AsprsClass.HIGH_VEGETATION),
    Semantic.TRUNK: int(AsprsClass.HIGH_VEGETATION),
}
"""Static SemanticKITTI class id (0..99) -> ASPRS code; the rest (vehicles, poles, signs,
fences, people) have no ASPRS class and stay 1 (unclassified)."""
