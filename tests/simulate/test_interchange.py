"""The `interchange` preset: an exit ramp whose guardrail turns away from the road, the edge
guardrail resuming at the gore, and a concrete median barrier that is not a guardrail."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import Semantic
from app.simulate.layout import build_scene
from app.simulate.road import Centerline


def _lateral(centerline: Centerline, xy: np.ndarray) -> np.ndarray:
    """Signed lateral offset (left positive) of points from the centreline polyline."""
    c = centerline[:, :2]
    nearest = np.argmin(((xy[:, None, :] - c[None, :, :]) ** 2).sum(-1), axis=1)
    heading = np.gradient(c, axis=0)[nearest]
    d = xy - c[nearest]
    return (heading[:, 0] * d[:, 1] - heading[:, 1] * d[:, 0]) / np.linalg.norm(heading, axis=1)


@pytest.mark.parametrize("seed", [701, 709])
def test_the_ramp_guardrail_turns_away_and_the_median_is_concrete_or_beam(seed: int) -> None:
    scene = build_scene("interchange", 30.0, np.random.default_rng(seed))
    again = build_scene("interchange", 30.0, np.random.default_rng(seed))
    assert [b.name for b in scene.bodies] == [b.name for b in again.bodies]  # deterministic
    barriers = [b for b in scene.bodies if b.name == "median-barrier"]
    rails = [np.asarray([p["base"] for p in g["poles"]]) for g in scene.guardrails]
    laterals = [_lateral(scene.centerline, r[:, :2]) for r in rails]
    # the ramp's outer guardrail: on the right, moving at least 8 m further right along it
    swing = [lat.min() - lat[: len(lat) // 4].mean() for lat in laterals if lat.mean() < -5.0]
    assert min(swing) < -8.0
    if barriers:  # no posts and no beam: a fence to SemanticKITTI, not a guardrail here
        (barrier,) = barriers
        assert barrier.semantic == Semantic.FENCE and barrier.guardrail == -1
        z = barrier.mesh.vertices[:, 2] - np.interp(
            barrier.mesh.vertices[:, 0], scene.centerline[:, 0], scene.centerline[:, 2]
        )
        assert 0.8 <= z.max() <= 1.1
        assert not any(abs(lat.mean()) < 1.0 for lat in laterals)
    else:
        assert any(abs(lat.mean()) < 1.0 for lat in laterals)  # the median beam instead
    assert len(scene.guardrails) >= 3  # left edge, ramp, edge after the gore


def test_both_median_kinds_occur_over_seeds() -> None:
    kinds = {
        any(
            b.name == "median-barrier"
            for b in build_scene("interchange", 30.0, np.random.default_rng(seed)).bodies
        )  # fmt: skip
        for seed in range(700, 706)
    }
    assert kinds == {True, False}
