"""Along the drive: a survey of kilometres is one street after another, and an operator goes
through it as the van did. A slider of metres along the trajectory and steps of `STEP_M` each
way put the camera above the drive there, looking ahead from behind and to the left; the mode's
tiles in focus follow the camera as they do when the user moves it.

The trajectory is the survey's frame poses (a map's recorded or traced path is one position per
frame row; with fewer than two positions, or a drive shorter than a slider step, there are no
drive controls).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from app.geometry.trajectory import arc_length

STEP_M = 100.0  # metres per step button
SLIDER_STEP_M = 10.0
VIEW_DISTANCE_M = 60.0  # from the camera to the point of the drive it looks at
# the camera's offset from that point, in the drive's frame: behind, left, above
VIEW_OFFSET = np.array([-0.4, 0.3, 1.0])


class Drive:
    """A trajectory (M, 3) in the scene's local coordinates: positions and headings by
    metres along it."""

    def __init__(self, positions: np.ndarray):
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        flat = np.column_stack([positions[:, :2], np.zeros(len(positions))])
        self.station = arc_length(flat)
        moved = np.r_[True, np.diff(self.station) > 0]  # stops repeat a station
        self.station, self.positions = self.station[moved], positions[moved]

    @property
    def length(self) -> float:
        return float(self.station[-1]) if len(self.station) else 0.0

    def at(self, metres: float) -> tuple[np.ndarray, np.ndarray]:
        """The position (3,) at `metres` along the drive (clamped to it) and the unit heading
        (2,) of the segment there."""
        s = float(np.clip(metres, 0.0, self.length))
        position = np.array([np.interp(s, self.station, self.positions[:, a]) for a in range(3)])
        segment = np.searchsorted(self.station, s, side="right") - 1
        k = int(np.clip(segment, 0, len(self.station) - 2))
        heading = self.positions[k + 1, :2] - self.positions[k, :2]
        return position, heading / max(float(np.linalg.norm(heading)), 1e-9)


def view_offset(heading: np.ndarray, distance: float = VIEW_DISTANCE_M) -> np.ndarray:
    """(3,) from the looked-at point to the camera: behind and left of the heading, above."""
    back, left, up = VIEW_OFFSET
    along = np.array([heading[0], heading[1], 0.0])
    side = np.array([-heading[1], heading[0], 0.0])
    offset = back * along + left * side + up * np.array([0.0, 0.0, 1.0])
    return offset / np.linalg.norm(offset) * distance


class DriveControls:
    """The "Drive" folder of one viewer tab on one survey: the slider and the step buttons."""

    def __init__(
        self,
        gui: Any,
        drive: Drive,
        ground_height: Callable[[np.ndarray], float],
        move_camera: Callable[[np.ndarray, np.ndarray], None],
        submit: Callable[..., Any],
    ):
        self.drive = drive
        self.ground_height = ground_height
        self.move_camera = move_camera
        self.metres: float | None = None
        self.folder = gui.add_folder("Drive", expand_by_default=False)
        with self.folder:
            self.slider = gui.add_slider(
                "Along the drive (m)", min=0.0, max=float(np.ceil(drive.length)),
                step=SLIDER_STEP_M, initial_value=0.0,
            )  # fmt: skip
            back = gui.add_button(f"Back {STEP_M:.0f} m")
            ahead = gui.add_button(f"Ahead {STEP_M:.0f} m")
        self.slider.on_update(lambda _: submit(self.go, float(self.slider.value)))
        back.on_click(lambda _: submit(self.step, -STEP_M))
        ahead.on_click(lambda _: submit(self.step, STEP_M))

    @classmethod
    def maybe(cls, gui: Any, trajectory: np.ndarray, *args: Any) -> DriveControls | None:
        """The controls for a local trajectory (M, 3), or None where there is no drive to go
        along (fewer than two positions, or shorter than a slider step)."""
        if len(trajectory) < 2:
            return None
        drive = Drive(trajectory)
        return cls(gui, drive, *args) if drive.length >= SLIDER_STEP_M else None

    def step(self, metres: float) -> None:
        self.go((self.metres or 0.0) + metres)

    def go(self, metres: float) -> None:
        """The camera above the drive at `metres` (clamped), looking ahead along it."""
        metres = float(np.clip(metres, 0.0, self.drive.length))
        if self.metres is not None and abs(metres - self.metres) < SLIDER_STEP_M / 2:
            return  # the slider following a step (rounded to its own step): already there
        self.metres = metres
        position, heading = self.drive.at(metres)
        look_at = np.array([position[0], position[1], self.ground_height(position[:2])])
        self.move_camera(look_at, view_offset(heading))
        if abs(float(self.slider.value) - metres) > SLIDER_STEP_M / 2:
            self.slider.value = float(np.round(metres / SLIDER_STEP_M) * SLIDER_STEP_M)

    def remove(self) -> None:
        self.folder.remove()
