"""Situation streets (`situations.py`): the objects each is built around."""

from __future__ import annotations

import numpy as np

from app.core.labels import Semantic
from app.simulate.situations import TOUCHING_GAP, build_situation


def test_parked_rows_hold_long_vehicles_some_touching() -> None:
    """Buses, lorries and caravans stand in the parking lanes among vans and cars, and some
    stand closer to the next one than a clustering voxel (a row that clusters as one)."""
    scene = build_situation("parked_rows", 20.0, np.random.default_rng(4))
    parked = [b for b in scene.bodies if b.instance > 0 and not b.moving]
    names = {b.name for b in parked}
    assert {"parked-bus", "parked-truck", "caravan", "parked-car"} <= names
    caravans = [b for b in parked if b.name == "caravan"]
    assert all(b.semantic == Semantic.OTHER_VEHICLE for b in caravans)
    vehicles = [b for b in parked if b.semantic in (Semantic.CAR, Semantic.BUS, Semantic.TRUCK,
                                                    Semantic.OTHER_VEHICLE)]  # fmt: skip
    # gaps between neighbours along each parking lane (the street runs along x here)
    touching = 0
    for side in (-1, 1):
        row = np.array(
            sorted(
                (b.mesh.vertices[:, 0].min(), b.mesh.vertices[:, 0].max())
                for b in vehicles
                if np.sign(b.mesh.vertices[:, 1].mean()) == side
            )
        )
        gaps = row[1:, 0] - row[:-1, 1]
        assert (gaps > 0.05).all()  # never overlapping
        touching += int((gaps < TOUCHING_GAP + 0.05).sum())
    assert touching >= 1
