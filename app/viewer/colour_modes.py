"""What the labelling view colours points by, besides their label: height above the ground
(to pick out kerbs, cars and canopies), the sensor's intensity (road markings, signs), and the
phantom model's confidence (where to look first), the camera's colour where a frame's image saw
the point (what the object is). Colours are mid-tone, never near white: the
viewer's background is white.
"""

from __future__ import annotations

import numpy as np

LABEL = "Label"
HEIGHT = "Height above ground"
INTENSITY = "Intensity"
CONFIDENCE = "Model confidence"
CAMERA = "Camera colour"
COLOUR_MODES = (LABEL, HEIGHT, INTENSITY, CONFIDENCE, CAMERA)

HEIGHT_RANGE = (-0.5, 8.0)  # metres above the ground from the first to the last ramp colour
NO_VALUE_RGB = np.array((150, 150, 150), dtype=np.float64)  # no intensity / no model label
# a blue -> cyan -> green -> yellow -> red ramp (turbo-like), mid-tone at both ends
RAMP = np.array(
    [(48, 18, 160), (30, 120, 230), (20, 190, 170), (90, 200, 60), (235, 190, 20), (200, 40, 20)],
    dtype=np.float64,
)
CONFIDENCE_RAMP = np.array([(210, 30, 30), (230, 170, 20), (40, 160, 60)], dtype=np.float64)


def ramp(value: np.ndarray, lo: float, hi: float, stops: np.ndarray = RAMP) -> np.ndarray:
    """(n, 3) uint8: `value` between lo and hi along the colour stops (clamped); NaN grey."""
    value = np.asarray(value, dtype=np.float64)
    t = np.clip((value - lo) / max(hi - lo, 1e-9), 0.0, 1.0) * (len(stops) - 1)
    t = np.nan_to_num(t, nan=0.0)
    k = np.minimum(t.astype(np.int64), len(stops) - 2)
    frac = (t - k)[:, None]
    rgb = stops[k] * (1.0 - frac) + stops[k + 1] * frac
    rgb[np.isnan(value)] = NO_VALUE_RGB
    return np.rint(rgb).astype(np.uint8)


def height_colors(height_above_ground: np.ndarray) -> np.ndarray:
    return ramp(height_above_ground, *HEIGHT_RANGE)


def intensity_colors(intensity: np.ndarray) -> np.ndarray:
    """Grey ramp between the 2nd and 98th percentile of the points given (sensors report in
    their own units: KITTI reflectance 0..1, LAS 0..65535); NaN (none recorded) mid grey."""
    value = np.asarray(intensity, dtype=np.float64)
    finite = value[np.isfinite(value)]
    if not len(finite):
        return np.tile(NO_VALUE_RGB.astype(np.uint8), (len(value), 1))
    lo, hi = np.percentile(finite, [2, 98])
    grey = 30 + 170 * np.clip((value - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    rgb = np.stack([grey, grey, grey], axis=1)
    rgb[~np.isfinite(value)] = NO_VALUE_RGB
    return np.rint(rgb).astype(np.uint8)


def confidence_colors(confidence: np.ndarray) -> np.ndarray:
    """Red (unsure, 0.25 or less: a four-class model's chance level) to green (sure); grey
    where the model gave no label."""
    return ramp(confidence, 0.25, 1.0, CONFIDENCE_RAMP)


def camera_colors(rgb: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The camera's colour where it saw the point, grey elsewhere."""
    out = np.tile(NO_VALUE_RGB.astype(np.uint8), (len(seen), 1))
    out[seen] = np.asarray(rgb)[seen]
    return out
