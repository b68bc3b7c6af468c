"""Camera instances: connected components of each class mask, split where the LiDAR depth jumps.

A mask component can hold several objects (a row of parked cars is one blob in the image) and,
at its rim and through windows, whatever lies behind them. Sorting the component's points by
depth and cutting at gaps larger than `depth_gap` gives depth layers; each layer with at least
`min_points` points is an instance. Whether an instance is an object or background showing
through is decided in 3D (`expansion.py`): background clusters are mostly off the masks.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.pipelines.clutter.masking import FrameMasking


def mask_components(class_map: np.ndarray) -> np.ndarray:
    """(H, W) int32 component id per pixel (8-connected, one class per component), -1 = none."""
    components = np.full(class_map.shape, -1, dtype=np.int32)
    next_id = 0
    for cls in np.unique(class_map[class_map > 0]):
        count, labels = cv2.connectedComponents((class_map == cls).astype(np.uint8), None, 8)
        inside = labels > 0
        components[inside] = labels[inside] - 1 + next_id
        next_id += count - 1
    return components


def camera_instances(
    masking: FrameMasking,
    components: np.ndarray,
    depth_gap: float,
    min_points: int,
    eligible: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) int32 instance id (a depth layer of a mask component) of each point, else -1.

    Only `eligible` points (the
    pipeline passes the points above the ground) form layers: the road in front of a car shows
    through the lower rim of its mask and would otherwise be the nearest layer.
    """
    n = len(masking.in_view)
    instance = np.full(n, -1, dtype=np.int32)
    seen = np.flatnonzero(masking.in_view)
    component = components[masking.rows, masking.cols]
    on_mask = component >= 0
    if eligible is not None:
        on_mask &= eligible[seen]
    points, component = seen[on_mask], component[on_mask]
    if len(points) == 0:
        return instance
    depth = masking.depth[points]
    order = np.lexsort((depth, component))
    points, component, depth = points[order], component[order], depth[order]
    new_layer = np.ones(len(points), dtype=bool)
    new_layer[1:] = (component[1:] != component[:-1]) | (np.diff(depth) > depth_gap)
    layer = np.cumsum(new_layer) - 1
    big = np.bincount(layer) >= min_points
    keep = big[layer]
    renumbered = np.cumsum(big) - 1  # instance ids 0..K-1 over the big layers
    instance[points[keep]] = renumbered[layer[keep]]
    return instance
