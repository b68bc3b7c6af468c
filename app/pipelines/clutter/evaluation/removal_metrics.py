"""The clutter run against reference labels: the paper's error matrix and SA / DA / AA, inside
the camera view and on the full 360 degree map.

References (SemanticKITTI ids; the simulator writes the same ids and a per-point `moving` flag):
- `dynamic`: the moving classes 252-259, or the simulator's `moving` flag;
- `clutter`: every movable class, parked or moving (cars, bicycles, buses, motorcycles, trams,
  trucks, other vehicles, persons, bicyclists, motorcyclists: 10-32 and 252-259).
Unlabelled (0) and outlier (1) points have no reference class and are left out of every score.
"""

from __future__ import annotations

import numpy as np

from app.core.labels import MOVABLE_IDS, MOVING_IDS, UNSCORED_IDS
from app.metrics.removal import dynamic_scores, error_matrix


def reference_masks(
    semantic: np.ndarray, moving: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per point: `scored`, `dynamic` (moving) and `clutter` (movable) reference flags."""
    semantic = np.asarray(semantic) & 0xFFFF
    dynamic = np.isin(semantic, MOVING_IDS)
    if moving is not None:
        dynamic |= np.asarray(moving).astype(bool)
    return {
        "scored": ~np.isin(semantic, UNSCORED_IDS),
        "dynamic": dynamic,
        "clutter": np.isin(semantic, MOVABLE_IDS) | dynamic,
    }


def removal_metrics(
    semantic: np.ndarray,
    removed: np.ndarray,
    in_view: np.ndarray,
    moving: np.ndarray | None = None,
) -> dict[str, dict[str, dict]]:
    """{scope: {reference: {"error_matrix": ..., "scores": SA/DA/AA}}} for scope in view / 360."""
    ref = reference_masks(semantic, moving)
    removed = np.asarray(removed, dtype=bool)
    out: dict[str, dict[str, dict]] = {}
    for scope, where in (("in_view", ref["scored"] & in_view), ("full", ref["scored"])):
        out[scope] = {}
        for kind in ("dynamic", "clutter"):
            truth = ref[kind][where]
            out[scope][kind] = {
                "error_matrix": error_matrix(truth, removed[where]).as_dict(),
                "scores": dynamic_scores(truth, removed[where]).as_dict(),
            }
    return out
