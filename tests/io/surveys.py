"""Small surveys built in memory for tests of how a drive is cut into tiles."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.io.survey import Frame, PointCloud, Survey


def there_and_back() -> Survey:
    """A van drives 60 m east between two walls 5 m to either side, turns and drives back
    0.5 m further left: each frame sees both walls within 10 m of it."""
    x = np.r_[np.arange(0.0, 61.0, 2.0), np.arange(60.0, -1.0, -2.0)[1:]]
    y = np.r_[np.zeros(31), np.full(30, 0.5)]
    along = np.arange(-10.0, 10.0, 0.1)
    frames = []
    for k, (px, py) in enumerate(zip(x, y, strict=True)):
        pose = np.eye(4)
        pose[:2, 3] = px, py
        walls = np.vstack([np.column_stack([along, np.full(200, side - py), np.zeros(200)])
                           for side in (5.0, -5.0)])  # fmt: skip

        def load(w=walls) -> PointCloud:
            return PointCloud(w.copy())

        frames.append(Frame(k, f"{k:06d}", pose, float(k), 400, _load_points=load))
    return Survey("there-and-back", Path("there-and-back"), "sim", frames)
