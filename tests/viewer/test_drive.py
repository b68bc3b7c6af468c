"""Along the drive: positions and headings by metres, and where the camera looks from."""

from __future__ import annotations

import numpy as np
import pytest

from app.viewer.drive import VIEW_DISTANCE_M, Drive, DriveControls, view_offset


def _corner() -> np.ndarray:
    """100 m east, a stop, then 50 m north (local coordinates, 2 m above the ground)."""
    east = np.column_stack([np.arange(0.0, 101.0, 10.0), np.zeros(11), np.full(11, 2.0)])
    north = np.column_stack([np.full(5, 100.0), np.arange(10.0, 51.0, 10.0), np.full(5, 2.0)])
    return np.vstack([east, east[-1:], north])


def test_positions_and_headings_by_metres_along_the_drive() -> None:
    drive = Drive(_corner())
    assert drive.length == pytest.approx(150.0)
    position, heading = drive.at(35.0)
    np.testing.assert_allclose(position, [35.0, 0.0, 2.0])
    np.testing.assert_allclose(heading, [1.0, 0.0])
    position, heading = drive.at(120.0)  # past the corner (and the stop): heading north
    np.testing.assert_allclose(position, [100.0, 20.0, 2.0])
    np.testing.assert_allclose(heading, [0.0, 1.0])
    np.testing.assert_allclose(drive.at(-5.0)[0], [0.0, 0.0, 2.0])  # clamped to the drive
    np.testing.assert_allclose(drive.at(1e6)[0], [100.0, 50.0, 2.0])


def test_the_camera_looks_ahead_from_behind_left_and_above() -> None:
    offset = view_offset(np.array([0.0, 1.0]))  # driving north
    assert np.linalg.norm(offset) == pytest.approx(VIEW_DISTANCE_M)
    assert offset[1] < 0 and offset[0] < 0 and offset[2] > 0  # south (behind), west (left), up


def test_no_drive_controls_without_a_drive() -> None:
    assert DriveControls.maybe(None, np.zeros((1, 3))) is None  # a map of one position
    assert DriveControls.maybe(None, np.array([[0.0, 0, 0], [3.0, 0, 0]])) is None  # 3 m
