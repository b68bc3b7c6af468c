"""Vehicle shape evidence: features per cluster, the classifier's file, and clutter mode taking a
vehicle-shaped track the camera never named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from app.core.errors import ConfigError, InputError
from app.io import open_survey
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.fusion import fuse
from app.pipelines.clutter.shapes import (
    FEATURES,
    MIN_VEHICLE_SPAN,
    ROTATING_MODEL,
    SHAPE_POINTS,
    ShapeInputs,
    ShapeNet,
    VehicleShapes,
    load_vehicle_shapes,
    shape_inputs,
)
from app.pipelines.clutter.tracking import Observation, track_clusters
from app.pipelines.clutter.training.shapes import (
    labelled_samples,
    scene_cycle,
    scores,
    street_samples,
    train_shapes,
    with_real,
)
from app.simulate.survey import SimulationConfig, simulate
from tests.pipelines.clutter.test_steps import box_surface, one_point_per_cluster


def test_features_tell_a_car_body_from_a_pole() -> None:
    car = box_surface((12, 3, 0.9), (4.4, 1.8, 1.4), step=0.1)
    pole = box_surface((8, -4, 1.5), (0.2, 0.2, 3.0), step=0.05)
    xyz = np.r_[car, pole]
    label = np.r_[np.zeros(len(car)), np.ones(len(pole))].astype(np.int32)
    above = xyz[:, 2].copy()
    inputs = shape_inputs(xyz, label, above, np.array([True, True, False]))
    rows = inputs.features
    assert rows.shape == (3, len(FEATURES)) and np.isnan(rows[2]).all()
    named = dict(zip(FEATURES, rows[0], strict=True))
    assert abs(named["length"] - 4.4) < 0.15 and abs(named["width"] - 1.8) < 0.15
    assert abs(named["top"] - 1.6) < 0.05 and abs(named["range"] - np.hypot(12, 3)) < 0.1
    pole_row = dict(zip(FEATURES, rows[1], strict=True))
    assert pole_row["length"] < 0.3 and pole_row["linearity"] > 0.8
    # the point branch sees each cluster in its own frame: along its long axis, across, height
    points = inputs.points
    assert points.shape == (3, SHAPE_POINTS, 3) and np.isnan(points[2]).all()
    along, across, height = points[0].T
    assert abs(np.ptp(along) - 4.4) < 0.2 and abs(np.ptp(across) - 1.8) < 0.2
    assert abs(along.mean()) < 0.3 and height.min() >= 0.19 and height.max() <= 1.61
    again = shape_inputs(xyz, label, above, np.array([True, True, False]))
    assert np.array_equal(again.points[:2], points[:2])  # drawn the same way every run


def test_a_trained_classifier_round_trips_and_a_bad_file_is_one_line(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    features = rng.normal(size=(400, len(FEATURES))).astype(np.float32)
    y = (features[:, 2] > 0).astype(np.int8)  # "long ones are vehicles"
    features[:, FEATURES.index("width")] = 2.0  # all as wide as a vehicle (MIN_VEHICLE_SPAN)
    # ... and their points reach far along their axis
    points = rng.uniform(-0.5, 0.5, (400, SHAPE_POINTS, 3)).astype(np.float32)
    points[:, :, 0] *= np.where(y == 1, 4.0, 1.0)[:, None]
    x = ShapeInputs(features, points)
    model = train_shapes(x, y, epochs=20, card={"sensor_kind": "rotating"})
    path = tmp_path / "shapes.pt"
    model.save(path)
    again = load_vehicle_shapes(path)
    assert np.allclose(again.probability(x), model.probability(x), atol=1e-6)
    assert ((again.probability(x) >= 0.5) == y.astype(bool)).mean() > 0.9
    assert again.card["sensor_kind"] == "rotating" and path.with_suffix(".json").is_file()
    bad = tmp_path / "bad.pt"
    torch.save({"state": {}, "mean": torch.zeros(3), "std": torch.ones(3)}, bad)
    with pytest.raises(InputError, match="bad.pt"):
        load_vehicle_shapes(bad)


def test_the_shipped_classifier_tells_vehicles_on_a_street_it_never_saw(tmp_path: Path) -> None:
    """Synthetic: a simulated street of a seed outside its training and validation seeds, parked
    cars, trailers and site machines among trees, lamps and signs."""
    street = tmp_path / "street"
    simulate(SimulationConfig(scene="shadow", length=10.0, seed=990, camera=False), street)
    x, y, _ = street_samples(street)
    assert y.sum() >= 20 and (1 - y).sum() >= 20
    got = scores(load_vehicle_shapes(ROTATING_MODEL), x, y, 0.5)
    assert got["precision"] > 80 and got["recall"] > 50, got  # measured 90 and 62


def test_clutter_mode_takes_a_vehicle_shaped_track_the_camera_never_named() -> None:
    """A car in deep shadow: in view in every frame, never masked, vehicle-shaped in 3D. Clutter
    mode removes it; without shape evidence, or in dynamic mode, it stays."""
    observations = []
    for i in range(5):
        observations.append(
            Observation(
                frame=i, time=0.1 * i, centroids=np.array([[12.0, 3.0, 0.9], [8.0, -4.0, 1.5]]),
                points=np.full(2, 300.0), camera_class=np.zeros(2, np.uint8),
                free_points=np.zeros(2), trackable=np.ones(2, bool), seen=np.ones(2, bool),
                vehicle=np.array([0.95, 0.05]),
            )
        )  # fmt: skip
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    assert tracks.vehicle_shape.tolist() == pytest.approx([0.95, 0.05])
    evidence = one_point_per_cluster(2, 5, in_view=True)
    clutter = fuse(evidence, tracks, ClutterConfig(mode="clutter"))
    assert all(r.tolist() == [True, False] for r in clutter)
    off = fuse(evidence, tracks, ClutterConfig(mode="clutter", vehicle_shapes=False))
    dynamic = fuse(evidence, tracks, ClutterConfig(mode="dynamic"))
    assert not any(r.any() for r in off) and not any(r.any() for r in dynamic)


def test_real_labelled_clusters_join_the_simulated_ones_with_their_weight(real_data: Path) -> None:
    """Real SemanticKITTI: its trackable clusters, labelled by the reference (vehicle or other)
    with the class most of their points hold, join simulated samples with a larger weight."""
    survey = open_survey(real_data / "semantickitti" / "sequences" / "05", "semantickitti")
    x, y, classes = labelled_samples([survey])
    assert len(y) == len(classes) == len(x.features) == len(x.points) > 100
    assert set(np.unique(classes[y == 1])) <= {10, 13, 16, 18, 20, 252, 256, 257, 258, 259}
    assert 70 in classes[y == 0] and y.sum() > 10  # vegetation among the others, some vehicles
    simulated = (
        ShapeInputs(np.zeros((5, len(FEATURES)), np.float32), np.zeros((5, SHAPE_POINTS, 3))),
        np.ones(5, np.int8),
        np.full(5, 10, np.uint16),
    )
    inputs, both, weight = with_real(simulated, (x, y, classes), 10.0)
    assert len(both) == len(weight) == len(inputs.features) == 5 + len(y)
    assert weight[:5].tolist() == [1.0] * 5 and (weight[5:] == 10.0).all()
    assert np.array_equal(both[5:], y)


def test_a_scene_cycle_names_known_scenes_only() -> None:
    assert scene_cycle("urban, shadow,parked_rows") == ("urban", "shadow", "parked_rows")
    with pytest.raises(ConfigError, match="--scenes.*'forest'"):
        scene_cycle("urban,forest")


def test_a_cluster_narrower_than_any_vehicle_is_none_whatever_the_network_says() -> None:
    """A network sure that everything is a vehicle still gives a pole or a sign plate 0: a
    vehicle spans at least MIN_VEHICLE_SPAN along one of its axes, seen from any side."""
    car = box_surface((12, 3, 0.9), (4.4, 1.8, 1.4), step=0.1)
    car_end = box_surface((12, -6, 0.9), (0.3, 1.6, 1.4), step=0.05)  # a car seen from behind
    pole = box_surface((8, -4, 1.5), (0.2, 0.2, 3.0), step=0.05)
    xyz = np.r_[car, car_end, pole]
    label = np.repeat([0, 1, 2], [len(car), len(car_end), len(pole)]).astype(np.int32)
    inputs = shape_inputs(xyz, label, xyz[:, 2].copy(), np.ones(3, bool))
    net = ShapeNet(len(FEATURES))
    with torch.no_grad():
        for parameter in net.parameters():
            parameter.zero_()
        net.head[-1].bias.fill_(10.0)  # every cluster a vehicle
    sure = VehicleShapes(
        net, np.zeros(len(FEATURES), np.float32), np.ones(len(FEATURES), np.float32), {}
    )
    p = sure.probability(inputs)
    assert p[0] > 0.99 and p[1] > 0.99 and p[2] == 0.0
    assert MIN_VEHICLE_SPAN < 1.4  # the narrowest car's width
