"""A missed object from a 2D box on the camera image: the object the camera sees in the box,
not the facade behind it, the road under it or the pole in front of it; nothing when the object
seen is an instance already. A synthetic street seen by a KITTI-like camera (x right, y down,
z forward; the scanner 1.7 m above the road, x forward, z up). The same on real SemanticKITTI
frames: tests/api/test_clutter_box_object.py."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.errors import ConfigError
from app.geometry.projection import project
from app.geometry.transforms import make_transform
from app.io.survey import Camera
from app.pipelines.clutter.config import ClutterConfig
from app.review.box_objects import PixelBox, checked_box, object_in_box

FX, CX, CY = 721.5, 609.6, 172.9
P = np.array([[FX, 0.0, CX, 0.0], [0.0, FX, CY, 0.0], [0.0, 0.0, 1.0, 0.0]])
W, H = 1242, 375
T = make_transform(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), np.zeros(3))


def _grid(x: tuple[float, float], y: tuple[float, float], z: tuple[float, float], step: float):
    axes = [np.arange(a, b + 1e-9, step) for a, b in (x, y, z)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def street() -> dict[str, np.ndarray]:
    """Road, a parked car 12 m ahead, a pole 1 m in front of it, a facade 25 m ahead."""
    return {
        "road": _grid((3.0, 40.0), (-12.0, 12.0), (-1.7, -1.7), 0.25),
        "car": np.concatenate(
            [
                _grid((12.0, 12.0), (-1.0, 1.0), (-1.5, -0.2), 0.05),  # its back, facing us
                _grid((12.0, 16.0), (1.0, 1.0), (-1.5, -0.2), 0.1),  # its left side
            ]
        ),  # fmt: skip
        "pole": _grid((11.0, 11.1), (0.3, 0.4), (-1.6, 2.0), 0.05),
        "facade": _grid((25.0, 25.0), (-12.0, 12.0), (-1.6, 4.0), 0.1),
    }


def scene() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    parts = street()
    xyz = np.concatenate(list(parts.values()))
    names = np.concatenate([np.full(len(v), k) for k, v in parts.items()])
    return xyz, names, parts


def box_round(uv: np.ndarray, margin: float = 6.0) -> PixelBox:
    return PixelBox(*(uv.min(axis=0) - margin), *(uv.max(axis=0) + margin))


def test_the_box_takes_the_object_not_what_lies_behind_in_front_or_under_it() -> None:
    xyz, names, _ = scene()
    proj = project(xyz, P, T, W, H)
    owner = np.full(len(xyz), -1, np.int32)
    box = box_round(proj.uv[(names == "car") & proj.in_image])
    inside = proj.in_image & box.holds(proj.uv)
    assert set(names[inside]) == {"road", "car", "pole", "facade"}  # the box holds all four
    got = object_in_box(xyz, proj, owner, box, ClutterConfig())
    assert set(names[got]) == {"car"}
    assert len(got) == int(((names == "car") & inside).sum())
    # the facade alone, boxed above the car: the facade
    top = PixelBox(box.u0, 0.0, box.u1, box.v0 - 20)
    assert set(names[object_in_box(xyz, proj, owner, top, ClutterConfig())]) == {"facade"}


def test_an_object_that_is_an_instance_already_gives_nothing() -> None:
    """The car is an instance: the box round it gives no points, never the facade behind."""
    xyz, names, _ = scene()
    proj = project(xyz, P, T, W, H)
    owner = np.where(names == "car", 0, -1).astype(np.int32)
    box = box_round(proj.uv[(names == "car") & proj.in_image])
    assert len(object_in_box(xyz, proj, owner, box, ClutterConfig())) == 0
    # on the road only (below the car, nothing above the ground): nothing
    road = PixelBox(box.u0, box.v1 + 40, box.u1, H)
    assert len(object_in_box(xyz, proj, np.full(len(xyz), -1), road, ClutterConfig())) == 0


def test_a_box_outside_the_image_is_refused_by_name() -> None:
    camera = Camera("image_2", P, T, W, H)
    assert checked_box(PixelBox(-50.0, -10.0, 40.0, 30.0), camera) == PixelBox(0.0, 0.0, 40.0, 30.0)
    with pytest.raises(ConfigError, match="box.*covers no pixel"):
        checked_box(PixelBox(2000.0, 10.0, 2100.0, 40.0), camera)
    assert PixelBox.spanning((30.0, 5.0), (10.0, 25.0)) == PixelBox(10.0, 5.0, 30.0, 25.0)
