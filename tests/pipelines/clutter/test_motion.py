"""Object motion by registration: parked cars stand still, creeping cars move."""

from __future__ import annotations

import numpy as np

from app.pipelines.clutter.motion import MAX_SHAPE_POINTS, object_shape, register, register_many
from app.pipelines.clutter.tracking import Observation, track_clusters


def car_side(x_from: float, x_to: float, step: float = 0.05, seed: int = 0) -> np.ndarray:
    """Points on the visible flank (y = 0) and rear (x = 0) of a 4.5 m x 1.8 m x 1.5 m car."""
    rng = np.random.default_rng(seed)
    x, z = np.meshgrid(np.arange(x_from, x_to, step), np.arange(0.3, 1.5, step))
    flank = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    y, z = np.meshgrid(np.arange(0.0, 1.8, step), np.arange(0.3, 1.5, step))
    rear = np.stack([np.zeros(y.size), y.ravel(), z.ravel()], axis=1)
    parts = [flank] + ([rear] if x_from <= 0.0 else [])
    return np.concatenate(parts) + rng.normal(0, 0.01, (sum(len(p) for p in parts), 3))


def test_parked_car_seen_from_passing_viewpoints_does_not_move() -> None:
    """Rear and first half of the flank, then the back half of the flank only: the centroid
    slides by more than a metre, the registered displacement stays near zero."""
    before = object_shape(car_side(0.0, 3.0, seed=1))
    after = object_shape(car_side(1.5, 4.5, seed=2))
    centroid_step = after.mean(axis=0) - before.mean(axis=0)
    assert np.linalg.norm(centroid_step[:2]) > 1.0
    fit = register(before, after, centroid_step)
    assert np.linalg.norm(fit.displacement[0, :2]) < 0.05
    assert fit.residual[0] < 0.05


def test_creeping_car_moves_by_its_step() -> None:
    before = object_shape(car_side(0.0, 4.5, seed=1))
    after = object_shape(car_side(0.0, 4.5, seed=2) + [0.12, 0.0, 0.0])
    fit = register(before, after, after.mean(axis=0) - before.mean(axis=0))
    assert abs(fit.displacement[0][0] - 0.12) < 0.02 and abs(fit.displacement[0][1]) < 0.02


def test_fast_car_is_found_from_the_predicted_step() -> None:
    """1.3 m in one frame (13 m/s): out of reach of the static start, found from the centroid."""
    before = object_shape(car_side(0.0, 4.5, seed=1))
    after = object_shape(car_side(0.0, 4.5, seed=2) + [1.3, 0.1, 0.0])
    fit = register(before, after, after.mean(axis=0) - before.mean(axis=0))
    assert np.allclose(fit.displacement[0, :2], [1.3, 0.1], atol=0.03)


def test_wall_sliding_along_itself_is_static() -> None:
    """A flat strip gives no hold along itself: the static start wins the tie."""
    before = object_shape(car_side(2.0, 8.0, seed=1))  # flank only: a plane
    after = object_shape(car_side(3.0, 9.0, seed=2))
    fit = register(before, after, after.mean(axis=0) - before.mean(axis=0))
    assert np.linalg.norm(fit.displacement[0, :2]) < 0.05


def test_no_overlap_is_reported_as_no_fit() -> None:
    fit = register(car_side(0.0, 2.0), car_side(0.0, 2.0) + [30.0, 0, 0], np.zeros(3))
    assert not np.isfinite(fit.residual[0])


def test_object_shape_is_thinned_and_capped() -> None:
    dense = car_side(0.0, 40.0, step=0.02)
    shape = object_shape(dense)
    assert len(shape) == MAX_SHAPE_POINTS
    assert np.array_equal(shape, object_shape(dense))  # deterministic


def test_tracks_use_registration_and_ignore_one_wrong_link() -> None:
    """A parked car seen while passing (centroid slides 0.3 m per frame) is static; a car
    creeping at 1 m/s moves; one link to a far neighbour does not make the parked car move."""
    observations = []
    for i in range(8):
        parked = car_side(0.3 * i, 0.3 * i + 2.5, seed=i) + [0.0, 6.0, 0.0]
        creeping = car_side(0.0, 4.5, seed=10 + i) + [0.1 * i, 0.0, 0.0]
        if i == 4:  # the parked car's cluster is a hedge 1.5 m away in this frame
            parked = car_side(0.0, 2.5, seed=i) + [1.5 + 0.3 * i, 6.0, 0.0]
        shapes = [object_shape(parked), object_shape(creeping)]
        observations.append(
            Observation(
                frame=i,
                time=0.1 * i,
                centroids=np.stack([s.mean(axis=0) for s in shapes]),
                points=np.array([len(s) for s in shapes], dtype=float),
                camera_class=np.full(2, 3, np.uint8),
                free_points=np.zeros(2),
                trackable=np.ones(2, bool),
                shapes=shapes,
            )
        )
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    parked, creeping = tracks.cluster_track[0]
    assert all(list(ids) == [parked, creeping] for ids in tracks.cluster_track)
    assert tracks.speed[parked] < 0.3
    assert abs(tracks.speed[creeping] - 1.0) < 0.2
    assert all(o.shapes is None for o in observations)  # freed as the tracker went


def test_batch_matches_one_by_one() -> None:
    """Objects registered together give what each gives alone (no pair crosses two objects),
    including a pair too small to fit."""
    before = [car_side(0.0, 4.5, seed=1), car_side(0.0, 2.0, seed=3) + [2.0, 0.5, 0.0]]
    after = [before[0] + [0.2, 0.0, 0.0], before[1] + [-0.1, 0.05, 0.0]]
    before.append(np.zeros((2, 3)))
    after.append(np.ones((5, 3)))
    predicted = np.array(
        [a.mean(axis=0) - b.mean(axis=0) for a, b in zip(after, before, strict=True)]
    )
    batch = register_many(before, after, predicted)
    for i in range(2):
        alone = register(before[i], after[i], predicted[i])
        assert np.allclose(batch.displacement[i], alone.displacement[0], atol=1e-9)
    assert np.allclose(batch.displacement[0, :2], [0.2, 0.0], atol=0.02)
    assert np.allclose(batch.displacement[1, :2], [-0.1, 0.05], atol=0.02)
    assert not np.isfinite(batch.residual[2]) and (batch.displacement[2] == 0).all()
