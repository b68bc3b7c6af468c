"""Standard views (CloudCompare's and CVAT's top / front / side), relative to the drive: the
camera keeps the point it looks at and its distance and swings to look down on it (the drive
pointing up the screen), along the drive, or across it from the right, or back to the oblique
view the viewer opens with. The drive's heading comes from the trajectory position nearest the
point looked at; a survey without a trajectory uses +x.
"""

from __future__ import annotations

import numpy as np

from app.viewer.drive import view_offset

PRESETS = ("Top", "Front", "Side", "Oblique")
HOTKEYS = {"Top": "T", "Front": "F", "Side": "S", "Oblique": "O"}
DISTANCE = (5.0, 300.0)  # metres: the camera's distance is kept within this
TILT = 0.02  # a straight-down (or level) camera has no defined "up": tilt it by this much


def heading_at(trajectory: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Unit heading (2,) of the trajectory segment nearest `xy` (local); +x without one."""
    positions = np.asarray(trajectory, dtype=np.float64).reshape(-1, 3)[:, :2]
    if len(positions) < 2:
        return np.array([1.0, 0.0])
    steps = np.diff(positions, axis=0)
    moving = np.hypot(*steps.T) > 1e-6
    if not moving.any():
        return np.array([1.0, 0.0])
    starts, steps = positions[:-1][moving], steps[moving]
    rel = np.asarray(xy, dtype=np.float64)[:2] - starts
    t = np.clip((rel * steps).sum(axis=1) / (steps * steps).sum(axis=1), 0.0, 1.0)
    gap = np.hypot(*(rel - t[:, None] * steps).T)
    step = steps[int(np.argmin(gap))]
    return step / np.linalg.norm(step)


def preset_offset(preset: str, heading: np.ndarray, distance: float) -> np.ndarray:
    """(3,) from the point looked at to the camera for a preset view."""
    if preset not in PRESETS:
        raise ValueError(f"unknown view {preset!r}; one of {', '.join(PRESETS)}")
    distance = float(np.clip(distance, *DISTANCE))
    along = np.array([heading[0], heading[1], 0.0])
    right = np.array([heading[1], -heading[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    direction = {
        "Top": up - TILT * along,  # from above, a hair behind: the drive points up the screen
        "Front": -along + TILT * up,  # from behind, looking along the drive
        "Side": right + TILT * up,  # from the right of the drive, looking across it
    }.get(preset)
    if direction is None:
        return view_offset(heading, distance)
    return direction / np.linalg.norm(direction) * distance
