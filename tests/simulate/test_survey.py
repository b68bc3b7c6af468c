"""A whole simulated survey: determinism, readers, ground truth checked against the scene."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from app.core.errors import InputError
from app.core.labels import GROUND_CLASSES, HIGH_CLASSES, PillarClass
from app.geometry.projection import project
from app.io import open_survey
from app.simulate.ground_truth import PILLAR_CELL, PILLAR_HEIGHT
from app.simulate.guardrail_distance import surface_distance
from app.simulate.survey import SimulationConfig, rebuild_scene, simulate

SMALL = SimulationConfig(scene="urban", length=14.0, seed=7, scanner="hdl64")


@pytest.fixture(scope="module")
def small_survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "urban"
    simulate(SMALL, out)
    return out


@pytest.fixture(scope="module")
def profile_survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "profile"
    simulate(SimulationConfig(scene="mixed", length=30.0, seed=3, scanner="profile"), out)
    return out


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_same_seed_same_bytes(small_survey: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    simulate(SMALL, again)
    assert tree_digest(small_survey) == tree_digest(again)
    other = tmp_path / "other"
    simulate(SMALL.model_copy(update={"seed": 8}), other)
    assert tree_digest(other) != tree_digest(small_survey)


def test_existing_output_is_refused(small_survey: Path) -> None:
    from app.core.errors import InputError

    with pytest.raises(InputError, match="already exists"):
        simulate(SMALL, small_survey)


def test_readers(small_survey: Path) -> None:
    sim = open_survey(small_survey, "sim")
    raw = open_survey(small_survey, "kitti-raw")
    assert len(sim) == len(raw) >= 10
    assert not raw.poses_estimated  # OXTS packets were written
    # the devkit poses are the world poses shifted to the first GNSS fix
    shift = sim.poses()[0, :3, 3] - raw.poses()[0, :3, 3]
    assert np.abs(raw.poses()[:, :3, 3] + shift - sim.poses()[:, :3, 3]).max() < 1e-3
    assert np.abs(raw.poses()[:, :3, :3] - sim.poses()[:, :3, :3]).max() < 1e-6
    frame = sim.frames[3]
    cloud, truth = frame.points(), frame.reference_labels()
    assert len(cloud) == frame.point_count and cloud.time is not None
    assert set(truth) == {"semantic", "instance", "moving", "pillar_class", "guardrail", "part",
                          "halo"}  # fmt: skip
    assert np.array_equal(raw.frames[3].points().xyz, cloud.xyz)


def test_a_truth_file_without_times_is_named(small_survey: Path, tmp_path: Path) -> None:
    """A frame's points take their times from its truth file (only that member is read): a
    file without them is one error naming it."""
    copy = tmp_path / "urban"
    shutil.copytree(small_survey, copy)
    sim = open_survey(copy, "sim")
    truth = copy / "ground_truth" / "labels" / f"{sim.frames[2].frame_id}.npz"
    with np.load(truth) as data:
        kept = {k: data[k] for k in data.files if k != "time"}
    np.savez_compressed(truth, **kept)
    assert len(sim.frames[2].reference_labels()["semantic"]) == sim.frames[2].point_count
    with pytest.raises(InputError, match=f"{truth.name}.*has no time"):
        sim.frames[2].points()


def test_moving_points_lie_in_their_objects_swept_volume(small_survey: Path) -> None:
    scene = rebuild_scene(SMALL)
    sim = open_survey(small_survey, "sim")
    movers: dict[int, list] = {}  # instance -> its bodies (a cyclist is bicycle + rider)
    for body in scene.bodies:
        if body.motion is not None:
            movers.setdefault(body.instance, []).append(body)
    checked = 0
    for frame in sim.frames:
        cloud, truth = frame.world_points(), frame.reference_labels()
        for instance, bodies in movers.items():
            sel = (truth["instance"] == instance) & truth["moving"]
            if not sel.any():
                continue
            R, t = bodies[0].motion.world_to_local(cloud.time[sel])
            local = np.einsum("nij,nj->ni", R, cloud.xyz[sel]) + t
            vertices = np.concatenate([b.mesh.vertices for b in bodies])
            lo, hi = vertices.min(0), vertices.max(0)
            margin = bodies[0].halo_margin + 0.1  # halo, plus 5 sigma of the 2 cm range noise
            inside = ((local >= lo - margin) & (local <= hi + margin)).all(axis=1)
            assert inside.all(), f"{bodies[0].name}: {(~inside).sum()} points outside"
            checked += int(sel.sum())
    assert checked > 100


def test_pillar_classes_follow_the_definition(small_survey: Path) -> None:
    """Recompute the phantom paper's pillar classes with a plain per-pillar loop."""
    scene = rebuild_scene(SMALL)
    sim = open_survey(small_survey, "sim")
    xyz = np.concatenate([f.world_points().xyz for f in sim.frames])
    truths = [f.reference_labels() for f in sim.frames]
    label = {k: np.concatenate([t[k] for t in truths]) for k in truths[0]}
    cell = np.floor(xyz[:, :2] / PILLAR_CELL).astype(np.int64)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    ground = scene.ground_height(xyz)
    rng = np.random.default_rng(0)
    for p in rng.choice(len(keys), size=min(400, len(keys)), replace=False):
        idx = np.flatnonzero(inverse == p)
        column = idx[xyz[idx, 2] - ground[idx] <= PILLAR_HEIGHT]
        objects = column[~np.isin(label["semantic"][column], list(GROUND_CLASSES))]
        moving = label["moving"][objects]
        if len(objects) < 3:
            expected = PillarClass.ground
        elif moving.sum() * 2 > len(objects):
            expected = PillarClass.phantom
        else:
            static = objects[~moving]
            high = np.isin(label["semantic"][static], list(HIGH_CLASSES)).sum()
            short = len(static) - high
            expected = PillarClass.high_object if high >= short else PillarClass.short_object
        assert (label["pillar_class"][idx] == expected).all()
    assert {0, 1, 2, 3} <= set(np.unique(label["pillar_class"]).tolist())


def test_guardrail_points_lie_on_their_models(profile_survey: Path) -> None:
    import json

    models = json.loads((profile_survey / "ground_truth" / "guardrails.json").read_text())
    sim = open_survey(profile_survey, "sim")
    kinds = set()
    for frame in sim.frames:
        cloud, truth = frame.world_points(), frame.reference_labels()
        for g, model in enumerate(models):
            sel = truth["guardrail"] == g
            if sel.sum() < 10:
                continue
            d = surface_distance(model, cloud.xyz[sel])
            assert np.quantile(d, 0.99) < 0.04, f"guardrail {g}: 99 % within {d.max():.3f} m"
            assert (truth["part"][sel] > 0).all()
            kinds.add(model["kind"])
    assert kinds == {"pipe", "beam"}


def test_instance_points_project_into_their_masks(small_survey: Path) -> None:
    import cv2

    sim = open_survey(small_survey, "sim")
    camera = sim.cameras["image_02"]
    hits = total = 0
    for frame in sim.frames:
        cloud, truth = frame.points(), frame.reference_labels()
        name = frame.frame_id
        mask = cv2.imread(
            str(small_survey / "ground_truth" / "masks" / f"{name}_instance.png"),
            cv2.IMREAD_UNCHANGED,
        )
        proj = project(cloud.xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
        sel = proj.in_image & (truth["instance"] > 0) & ~truth["halo"]
        u, v = np.floor(proj.uv[sel]).astype(int).T
        seen = mask[v, u]
        visible = seen > 0  # points the camera sees on some object (not occluded by stuff)
        hits += int((seen[visible] == truth["instance"][sel][visible]).sum())
        total += int(visible.sum())
    assert total > 1000
    assert hits / total >= 0.95, f"{hits / total:.1%}"


def test_trajectory_at_scanner_rate(profile_survey: Path) -> None:
    rows = np.loadtxt(profile_survey / "trajectory.txt")
    assert np.diff(rows[:, 0]) == pytest.approx(0.01)  # 100 profiles per second
    poses = np.loadtxt(profile_survey / "poses.txt")
    mid = np.round((np.arange(len(poses)) / 10 + 0.05) * 100).astype(int)
    assert np.allclose(rows[mid, 1:], poses)


def test_pose_noise(tmp_path: Path) -> None:
    config = SimulationConfig(scene="highway", length=20.0, seed=1, camera=False,
                              pose_noise_m=0.05, pose_noise_deg=0.1)  # fmt: skip
    out = tmp_path / "noisy"
    simulate(config, out)
    measured = np.loadtxt(out / "poses.txt").reshape(-1, 3, 4)
    exact = np.loadtxt(out / "ground_truth" / "poses.txt").reshape(-1, 3, 4)
    error = np.linalg.norm(measured[:, :, 3] - exact[:, :, 3], axis=1)
    assert 0.03 < np.median(error) < 0.15  # 3D error of 5 cm per axis
    sim = open_survey(out, "sim")
    assert np.allclose(sim.poses()[:, :3, :4], measured)
    # the OXTS packets carry the same noisy poses (shifted to the first fix)
    raw = open_survey(out, "kitti-raw").poses()
    assert (
        np.abs((raw[:, :3, 3] - raw[0, :3, 3]) - (measured[:, :, 3] - measured[0, :, 3])).max()
        < 1e-3
    )


def test_fixed_drive_speed_keeps_the_seeds_street() -> None:
    """A fixed speed changes the drive only: the street's bodies are the seed's (surveys of
    several lengths at one speed differ only in length, bench.scale)."""
    drawn = rebuild_scene(SimulationConfig(scene="mixed", length=120.0, seed=5))
    fixed = rebuild_scene(SimulationConfig(scene="mixed", length=120.0, seed=5, drive_speed=6.0))
    assert fixed.duration == pytest.approx(120.0 / 6.0)
    assert drawn.duration != pytest.approx(fixed.duration)
    assert [b.name for b in fixed.bodies] == [b.name for b in drawn.bodies]
    parked = [i for i, b in enumerate(drawn.bodies) if b.motion is None]
    for i in parked:
        assert np.array_equal(fixed.bodies[i].mesh.vertices, drawn.bodies[i].mesh.vertices)
    with pytest.raises(ValueError, match="drive_speed"):
        SimulationConfig(drive_speed=50.0)
