"""The clutter pipeline's steps on small synthetic scenes with known answers."""

from __future__ import annotations

import numpy as np

from app.io.survey import Camera
from app.pipelines.clutter.clusters import frame_clusters, object_hosts, voxel_components
from app.pipelines.clutter.config import ClutterConfig
from app.pipelines.clutter.expansion import cluster_sizes, expand_instances
from app.pipelines.clutter.freespace import free_groups, off_ground
from app.pipelines.clutter.fusion import FrameEvidence, fuse
from app.pipelines.clutter.instances import camera_instances, mask_components
from app.pipelines.clutter.masking import mask_points, pad_mask
from app.pipelines.clutter.motion import object_shape
from app.pipelines.clutter.tracking import Observation, track_clusters

RNG = np.random.default_rng(0)


def box(center, size, n) -> np.ndarray:
    return np.asarray(center) + (RNG.random((n, 3)) - 0.5) * np.asarray(size)


def ground(extent=20.0, n=4000) -> np.ndarray:
    xy = (RNG.random((n, 2)) - 0.5) * 2 * extent
    return np.c_[xy, RNG.normal(0, 0.01, n)]


def forward_camera(width=400, height=200, f=200.0) -> Camera:
    """A camera looking along +x of the sensor (x forward, y left, z up)."""
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # camera x right, y down, z forward
    P = np.array([[f, 0, width / 2, 0], [0, f, height / 2, 0], [0, 0, 1, 0]], dtype=float)
    return Camera("cam", P, T, width, height)


def test_voxel_components_separate_objects_and_join_touching_voxels() -> None:
    a = box((0, 0, 1), (1, 1, 1), 300)
    b = box((5, 0, 1), (1, 1, 1), 300)
    label = voxel_components(np.r_[a, b], 0.3)
    assert len(np.unique(label[:300])) == 1 and len(np.unique(label[300:])) == 1
    assert label[0] != label[300]


def test_frame_clusters_leave_the_ground_out() -> None:
    xyz = np.r_[
        ground(), box((6, 2, 1.05), (4, 1.8, 1.4), 800), box((6, -4, 1.2), (0.5, 0.5, 1.6), 200)
    ]
    clusters = frame_clusters(xyz, 0.3, 1.0, 0.25, 80.0)
    assert (clusters.label[:4000] == -1).mean() > 0.99
    assert len(np.unique(clusters.label[4000:4800])) == 1
    assert clusters.label[4000] != clusters.label[4800]
    sized = cluster_sizes(xyz, clusters).within(12.0, 4.5)
    assert sized[clusters.label[4000]]


def test_padding_grows_masks_by_the_buffer() -> None:
    mask = np.zeros((100, 100), bool)
    mask[50, 50] = True
    grown = pad_mask(mask, 30)
    assert grown[50, 80] and grown[20, 50] and not grown[50, 81] and not grown[10, 10]


def test_depth_layers_split_a_mask_and_ground_is_not_a_layer() -> None:
    camera = forward_camera()
    car = box((10, 0, 0.8), (0.2, 2.0, 1.2), 400)
    wall = box((25, 0, 1.5), (0.2, 8.0, 3.0), 400)
    road = np.c_[RNG.uniform(6, 9, 200), RNG.uniform(-1, 1, 200), np.zeros(200)]
    xyz = np.r_[car, wall, road]
    class_map = np.zeros((camera.height, camera.width), np.uint8)
    class_map[:, :] = 3  # everything under one car mask
    masking = mask_points(xyz, camera, class_map, 0)
    assert masking.in_view.all()
    eligible = np.r_[np.ones(800, bool), np.zeros(200, bool)]
    instance = camera_instances(masking, mask_components(class_map), 1.5, 5, eligible)
    assert len(np.unique(instance[:400])) == 1 and len(np.unique(instance[400:800])) == 1
    assert instance[0] != instance[400] and instance[0] >= 0
    assert (instance[800:] == -1).all()


def test_expansion_takes_objects_whole_and_only_the_masked_part_of_background() -> None:
    car = box((8, 0, 1.05), (4, 1.8, 1.4), 600)
    hedge = box((8, 3, 1.2), (30, 0.6, 1.6), 3000)  # background, far too long
    xyz = np.r_[ground(), car, hedge]
    clusters = frame_clusters(xyz, 0.3, 1.0, 0.25, 80.0)
    sized = cluster_sizes(xyz, clusters).within(12.0, 4.5)
    n = len(xyz)
    in_view = np.zeros(n, bool)
    in_view[4000:4300] = True
    in_view[4600 : 4600 + 150] = True  # the camera sees the end of the hedge, mostly masked
    instance = np.full(n, -1, np.int32)
    mask_class = np.zeros(n, np.uint8)
    instance[4000:4300] = 0  # half the car is on the mask, its other half is out of view
    mask_class[4000:4300] = 3
    hedge_masked = 4600 + np.arange(100)
    instance[hedge_masked] = 1
    mask_class[hedge_masked] = 3
    grown = expand_instances(xyz, clusters, instance, mask_class, in_view, 0.5, sized, 0.0)
    assert grown.removed[4000:4600].all()  # the whole car, out-of-view half included
    # the hedge is chosen but too long to be an object: its masked points go, the rest stays
    assert grown.removed[hedge_masked].all()
    assert not grown.removed[4600 + 100 :].any()
    assert grown.cluster_class[clusters.label[4000]] == 3
    assert grown.cluster_class[clusters.label[4600]] == 0


def test_expansion_takes_no_more_than_an_object_of_the_class_can_be() -> None:
    """A person standing under a market stall's awning is one cluster with the stall: the
    person's mask takes only its own points there, not the 3 m stall; a person standing
    alone goes whole (the parts the mask missed too)."""
    counter, awning = (
        box((8, 0, 0.55), (3.0, 1.0, 0.7), 800),
        box((8, -1, 2.0), (3, 2.5, 0.05), 800),
    )
    stall = np.r_[counter, awning]
    under = box((8, -0.75, 0.9), (0.4, 0.4, 1.8), 300)  # touches the counter and the awning
    alone = box((8, 6, 0.9), (0.5, 0.4, 1.8), 300)
    xyz = np.r_[ground(), stall, under, alone]
    clusters = frame_clusters(xyz, 0.3, 1.0, 0.1, 80.0)
    first_under, first_alone = 5600, 5900
    assert clusters.label[4000] == clusters.label[first_under]  # the person joins the stall
    sizes = cluster_sizes(xyz, clusters)
    sized = sizes.within(12.0, 4.5)
    n = len(xyz)
    in_view = np.ones(n, bool)
    instance = np.full(n, -1, np.int32)
    mask_class = np.zeros(n, np.uint8)
    instance[first_under : first_under + 250] = 0  # most of each person masked
    instance[first_alone : first_alone + 250] = 1
    mask_class[instance >= 0] = 1  # person
    args = (xyz, clusters, instance, mask_class, in_view, 0.1, sized, 0.0, 0.1)
    unbounded = expand_instances(*args)
    bounded = expand_instances(*args, sizes=sizes)
    assert unbounded.removed[4000:5600].all()  # without the bound: the stall went with them
    assert not bounded.removed[4000:5600].any()
    above = clusters.label >= 0  # (the feet are ground: halo_radius takes them, 0 here)
    masked_under = np.arange(first_under, first_under + 250)
    assert bounded.removed[masked_under[above[masked_under]]].all()
    assert not bounded.removed[first_under + 250 : first_alone].any()
    whole_alone = np.arange(first_alone, first_alone + 300)
    assert bounded.removed[whole_alone[above[whole_alone]]].all()  # its unmasked part too
    assert bounded.cluster_class[clusters.label[first_alone]] == 1
    assert bounded.cluster_class[clusters.label[first_under]] == 0


PERSON_START = 5600  # the person's first point in `_stall_with_person`'s points


def _stall_with_person(*extra: np.ndarray):
    """A market stall (counter, awning above head height) with a person at its counter, plus
    `extra` points: (points, clusters, sizes, the person's masked points as instance 0)."""
    counter = box((8, 0, 0.55), (3.0, 1.0, 0.7), 800)
    awning = box((8, -1, 2.4), (3, 2.5, 0.05), 800)  # above the person's head
    person = box((8, -0.75, 0.9), (0.4, 0.4, 1.8), 300)
    xyz = np.r_[ground(), counter, awning, person, *extra]
    clusters = frame_clusters(xyz, 0.3, 1.0, 0.1, 80.0)
    assert clusters.label[4000] == clusters.label[PERSON_START]  # the person joins the stall
    instance = np.full(len(xyz), -1, np.int32)
    instance[PERSON_START : PERSON_START + 250] = 0
    return xyz, clusters, cluster_sizes(xyz, clusters), instance


def _grown(xyz, clusters, sizes, instance, min_mask_fraction: float = 0.7, bounded: bool = True):
    """The expansion of the instances, bounded by what an object of the class can be (or not:
    `sizes` not given)."""
    mask_class = np.where(instance >= 0, 1, 0).astype(np.uint8)
    args = (xyz, clusters, instance, mask_class, np.ones(len(xyz), bool), min_mask_fraction)
    bound = {"sizes": sizes} if bounded else {}
    return expand_instances(*args, sizes.within(12.0, 4.5), 0.0, 0.1, **bound)


def test_a_person_merged_with_a_stall_gives_up_its_masked_points() -> None:
    """However little of the stall's cluster the person's mask covers (below
    min_mask_fraction), the person's masked points go; those the mask bled onto the awning
    above or the counter's far end stay, as does the rest of the stall."""
    xyz, clusters, sizes, instance = _stall_with_person()
    awning_bled = 4800 + np.flatnonzero(
        np.linalg.norm(xyz[4800:5600, :2] - [8, -0.75], axis=1) < 0.3
    )
    counter_end = 4000 + np.flatnonzero(xyz[4000:4800, 0] > 9.3)[:20]
    instance[awning_bled] = 0
    instance[counter_end] = 0
    grown = _grown(xyz, clusters, sizes, instance)
    above = clusters.label >= 0
    masked = np.arange(PERSON_START, PERSON_START + 250)
    assert grown.removed[masked[above[masked]]].all()
    assert not grown.removed[awning_bled].any() and not grown.removed[counter_end].any()
    assert grown.removed[4000:5600].sum() == 0
    unbounded = _grown(xyz, clusters, sizes, instance, bounded=False)
    assert not unbounded.removed[masked].any()  # unbounded: not chosen


def test_a_merged_persons_points_are_found_at_its_densest_spot_not_its_mean() -> None:
    """A mask bled onto a tree trunk beside the person (the same depth layer) pulls the
    instance's mean off the person: the person's masked points still go, the trunk's stay."""
    trunk = box((8.0, 0.68, 1.2), (0.25, 0.25, 2.2), 220)  # 1.4 m away, against the counter
    xyz, clusters, sizes, instance = _stall_with_person(trunk)
    trunk_start = 5900
    assert clusters.label[trunk_start] == clusters.label[PERSON_START]
    bled = np.arange(trunk_start, trunk_start + 180)  # most of the trunk under the bled mask
    instance[bled] = 0
    centre = xyz[instance == 0, :2].mean(axis=0)
    assert np.linalg.norm(centre - [8, -0.75]) > 0.5  # the mean is off the person
    above = clusters.label >= 0
    masked = np.arange(PERSON_START, PERSON_START + 250)
    # the mask covers little of the cluster (not chosen), then much of it (chosen): the same
    for min_mask_fraction in (0.7, 0.05):
        grown = _grown(xyz, clusters, sizes, instance, min_mask_fraction)
        assert grown.removed[masked[above[masked]]].all()
        assert not grown.removed[bled].any() and not grown.removed[4000:5600].any()


def _observations(positions: list[np.ndarray], camera_class: int = 3) -> list[Observation]:
    return [
        Observation(
            frame=i,
            time=0.1 * i,
            centroids=np.asarray(p, dtype=float),
            points=np.full(len(p), 100.0),
            camera_class=np.full(len(p), camera_class, np.uint8),
            free_points=np.zeros(len(p)),
            trackable=np.ones(len(p), bool),
        )
        for i, p in enumerate(positions)
    ]


def test_tracking_links_a_moving_and_a_parked_car() -> None:
    frames = [[[10 + 1.0 * i, 0, 1], [20, 5, 1]] for i in range(6)]  # 10 m/s and parked
    tracks = track_clusters(_observations(frames), gate=2.5, min_frames=3)
    assert len(tracks.tracks) == 2
    moving = tracks.cluster_track[0][0]
    assert all(ids[0] == moving for ids in tracks.cluster_track)
    assert abs(tracks.speed[moving] - 10.0) < 0.1
    assert tracks.speed[tracks.cluster_track[0][1]] < 0.1
    assert (tracks.camera_class == 3).all()


def test_fusion_modes() -> None:
    frames = [[[10 + 1.0 * i, 0, 1], [20, 5, 1]] for i in range(4)]
    tracks = track_clusters(_observations(frames), gate=2.5, min_frames=3)
    # per frame: 4 points, 2 of the moving car (cluster 0), 2 of the parked one (cluster 1)
    evidence = [
        FrameEvidence(
            in_view=np.array([i == 0] * 4),  # the camera sees the cars only in frame 0
            camera_removed=np.array([True] * 4) & (i == 0),
            padded=np.array([True] * 4) & (i == 0),
            cluster=np.array([0, 0, 1, 1], np.int32),
            free=np.zeros(4, bool),
        )
        for i in range(4)
    ]
    dynamic = fuse(evidence, tracks, ClutterConfig(mode="dynamic", min_speed=2.0))
    clutter = fuse(evidence, tracks, ClutterConfig(mode="clutter", min_speed=2.0))
    for i in range(4):
        assert dynamic[i].tolist() == [True, True, False, False]  # only the car that moved
        assert clutter[i].all()  # both cars, after they left the view too


def test_free_ground_points_stay_unless_they_touch_a_free_object() -> None:
    """Road points DUFOMap calls free (grazing rays) stay; the feet of a free walker go."""
    road = ground(extent=10.0, n=2000)
    walker = box([3.0, 0.0, 0.9], [0.5, 0.5, 1.8], 300)
    feet = box([3.0, 0.0, 0.1], [0.5, 0.5, 0.2], 40)
    xyz = np.concatenate([road, walker, feet])
    is_ground = np.r_[np.ones(len(road), bool), np.zeros(len(walker), bool), np.ones(40, bool)]
    free = np.zeros(len(xyz), bool)
    free[:200] = True  # grazing-ray noise on the road, away from the walker
    free[len(road) :] = True  # the walker and its feet
    far_from_walker = np.linalg.norm(road[:200, :2] - [3.0, 0.0], axis=1) > 1.0
    kept = off_ground(free, xyz, is_ground, radius=0.3)
    assert not kept[:200][far_from_walker].any()
    assert kept[len(road) :].all()
    assert (kept == free).sum() >= len(xyz) - 200


def test_clutter_mode_holds_a_class_through_a_missed_mask() -> None:
    """A parked car the camera sees in 4 frames and classes in 3 (the mask misses it in the
    shadow of frame 2) goes in frame 2 too, when 3 of 4 reaches min_class_share."""
    observations = _observations([[[20, 5, 1]] for _ in range(4)])
    for i, obs in enumerate(observations):
        obs.seen = np.array([True])
        obs.camera_class = np.array([0 if i == 2 else 3], np.uint8)
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    assert tracks.class_share.tolist() == [0.75]
    evidence = [
        FrameEvidence(
            in_view=np.ones(2, bool),
            camera_removed=np.full(2, i != 2),
            padded=np.full(2, i != 2),
            cluster=np.zeros(2, np.int32),
            free=np.zeros(2, bool),
        )
        for i in range(4)
    ]
    held = fuse(evidence, tracks, ClutterConfig(mode="clutter", min_class_share=0.5))
    strict = fuse(evidence, tracks, ClutterConfig(mode="clutter", min_class_share=1.0))
    assert all(r.all() for r in held)
    assert not strict[2].any() and strict[1].all()


def test_clutter_mode_outvotes_a_mask_the_track_rarely_had() -> None:
    """A kiosk the camera sees in 4 frames and calls a car in 1: with outvote_masks only the
    points on that frame's instance go (not its whole cluster), and it is not carried out of
    the view; without, the whole cluster goes there and in the frame the camera cannot see it."""
    observations = _observations([[[20, 5, 1]] for _ in range(5)])
    for i, obs in enumerate(observations):
        obs.seen = np.array([i < 4])
        obs.camera_class = np.array([3 if i == 1 else 0], np.uint8)
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    assert tracks.class_share.tolist() == [0.25]
    assert tracks.seen_frames.tolist() == [4]
    evidence = [
        FrameEvidence(
            in_view=np.full(4, i < 4),
            camera_removed=np.full(4, i == 1),  # the whole cluster, grown from one instance
            padded=np.full(4, i == 1),
            cluster=np.zeros(4, np.int32),
            free=np.zeros(4, bool),
            instance=np.array([0, 0, -1, -1] if i == 1 else [-1] * 4, np.int32),
        )
        for i in range(5)
    ]
    kept = fuse(evidence, tracks, ClutterConfig(mode="clutter", outvote_masks=False))
    voted = fuse(evidence, tracks, ClutterConfig(mode="clutter", outvote_masks=True))
    assert kept[1].all() and kept[4].all()  # whole cluster, and carried out of the view
    assert voted[1].tolist() == [True, True, False, False]
    assert not voted[4].any() and not voted[0].any()
    dynamic = fuse(evidence, tracks, ClutterConfig(mode="dynamic", outvote_masks=True))
    assert not any(r.any() for r in dynamic)  # the vote is a clutter-mode rule


def box_surface(center, size, step=0.15) -> np.ndarray:
    """Points on the six faces of a box, `step` apart (what a scanner sees of a solid)."""
    half = np.asarray(size) / 2
    faces = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        gu = np.arange(-half[u], half[u] + 1e-9, step)
        gv = np.arange(-half[v], half[v] + 1e-9, step)
        uu, vv = (g.ravel() for g in np.meshgrid(gu, gv))
        for sign in (-1.0, 1.0):
            face = np.zeros((len(uu), 3))
            face[:, axis], face[:, u], face[:, v] = sign * half[axis], uu, vv
            faces.append(face)
    return np.concatenate(faces) + np.asarray(center)


def one_point_per_cluster(clusters: int, frames: int, in_view: bool) -> list[FrameEvidence]:
    """Frames of `clusters` points, point k on cluster k, no camera mask, nothing free."""
    return [
        FrameEvidence(
            in_view=np.full(clusters, in_view),
            camera_removed=np.zeros(clusters, bool),
            padded=np.zeros(clusters, bool),
            cluster=np.arange(clusters, dtype=np.int32),
            free=np.zeros(clusters, bool),
        )
        for _ in range(frames)
    ]


def test_a_track_nobody_classed_moved_when_fast_in_one_direction() -> None:
    """Outside the camera's view, surfaces registered frame to frame: a car driving away at
    8 m/s moves; a parked car whose clusters jitter back and forth by 0.4 m and a fence whose
    visible part slides along at 1.5 m/s do not, nor does a car seen in too few frames."""
    jitter = [0.0, 0.4, 0.0, 0.4, 0.0, 0.4]
    objects = [
        lambda i: box_surface((10 + 0.8 * i, 0, 1.0), (4.2, 1.8, 1.4)),  # driving away
        lambda i: box_surface((20 + jitter[i], 6, 1.0), (4.2, 1.8, 1.4)),  # parked, jittering
        lambda i: box_surface((0.15 * i, -8, 0.6), (6.0, 0.1, 1.2)),  # a fence sliding
    ]
    observations = []
    for i in range(6):
        shapes = [object_shape(make(i), seed=k) for k, make in enumerate(objects)]
        observations.append(
            Observation(
                frame=i, time=0.1 * i, centroids=np.stack([c.mean(axis=0) for c in shapes]),
                points=np.full(3, 300.0), camera_class=np.zeros(3, np.uint8),
                free_points=np.zeros(3), trackable=np.ones(3, bool), shapes=shapes,
                top=np.array([1.7, 1.7, 1.2]),
            )
        )  # fmt: skip
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    car, parked, fence = (tracks.cluster_track[0][k] for k in range(3))
    assert abs(tracks.surface_speed[car] - 8.0) < 0.5 and tracks.straightness[car] > 0.99
    assert tracks.straightness[parked] < 0.5 and tracks.surface_speed[fence] < 1.0
    evidence = one_point_per_cluster(3, 6, in_view=False)
    moved = fuse(evidence, tracks, ClutterConfig(mode="dynamic"))
    assert all(r.tolist() == [True, False, False] for r in moved)
    off = fuse(evidence, tracks, ClutterConfig(mode="dynamic", track_motion=False))
    assert not any(r.any() for r in off)
    brief = fuse(evidence, tracks, ClutterConfig(mode="dynamic", min_motion_frames=7))
    assert not any(r.any() for r in brief)


def test_a_curb_with_free_points_is_not_an_object_that_moved() -> None:
    """Rays graze a curb followed over the frames and DUFOMap flags a fifth of it free: the curb
    did not move (its free points are judged one by one); a cart as free stands tall and went."""
    observations = [
        Observation(
            frame=i, time=0.1 * i, centroids=np.array([[12.0, 5.0, 0.1], [20.0, -4.0, 0.8]]),
            points=np.full(2, 300.0), camera_class=np.zeros(2, np.uint8),
            free_points=np.full(2, 60.0), trackable=np.ones(2, bool), top=np.array([0.13, 1.5]),
        )
        for i in range(6)
    ]  # fmt: skip
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    assert np.allclose(tracks.free_fraction, 0.2)
    moved = fuse(one_point_per_cluster(2, 6, in_view=False), tracks, ClutterConfig(mode="dynamic"))
    assert all(r.tolist() == [False, True] for r in moved)


def test_a_walking_person_moves_by_its_lower_body() -> None:
    """A person the camera classed, walking at 1.2 m/s whose torso the registration follows
    poorly, moves by its lower body; a person standing and swaying does not."""
    observations = []
    for i in range(8):
        centroids = np.array([[5.0 + 0.12 * i, 3.0, 1.0], [8.0, -3.0, 1.0]])
        observations.append(
            Observation(
                frame=i, time=0.1 * i, centroids=centroids, points=np.full(2, 150.0),
                camera_class=np.full(2, 1, np.uint8), free_points=np.zeros(2),
                trackable=np.ones(2, bool), seen=np.ones(2, bool),
                low_centroids=centroids + [[0.0, 0.0, -0.5], [0.04 * (-1) ** i, 0.0, -0.5]],
            )
        )  # fmt: skip
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    walker, standing = tracks.cluster_track[0]
    assert abs(tracks.walk_speed[walker] - 1.2) < 0.05 and tracks.walk_speed[standing] < 0.2
    evidence = one_point_per_cluster(2, 8, in_view=True)
    # the walker's registered speed said 0.4 m/s (noisy), below min_speed
    tracks.speed[:] = [0.4, 0.6]
    by_body = fuse(evidence, tracks, ClutterConfig(mode="dynamic", min_speed=1.0))
    by_registration = fuse(
        evidence, tracks, ClutterConfig(mode="dynamic", min_speed=1.0, walk_measure="registered")
    )
    assert all(r.tolist() == [True, False] for r in by_body)
    assert not any(r.any() for r in by_registration)


def test_loose_pieces_and_tyres_belong_to_their_object() -> None:
    """A far car's window-split piece (too small to track) 0.6 m from its body and its tyres'
    ground-level points go with the body's cluster; a road point 1 m away and a piece 2 m away
    belong to nothing."""
    body = box_surface((20, 0, 0.7), (4.0, 1.8, 1.0), step=0.1)
    n = len(body)
    piece = box((20, 0, 1.75), (1.0, 1.0, 0.1), 8)  # the roof, 0.5 m above the body's top
    tyres = box((19, 0.9, 0.05), (0.3, 0.2, 0.1), 10)
    road = np.array([[20.0, 2.3, 0.0]])
    stray = box((20, 5, 1.0), (0.3, 0.3, 0.3), 8)
    xyz = np.r_[body, piece, tyres, road, stray]
    label = np.r_[np.zeros(n), np.ones(8), -np.ones(11), np.full(8, 2)].astype(np.int32)
    trackable = np.array([True, False, False])
    near_ground = np.r_[np.zeros(n + 8, bool), np.ones(11, bool), np.zeros(8, bool)]
    host = object_hosts(xyz, label, trackable, near_ground, 0.3, 0.8)
    assert (host[:n] == -1).all()  # the body is tracked itself
    assert (host[n : n + 8] == 0).all() and (host[n + 8 : n + 18] == 0).all()
    assert host[n + 18] == -1 and (host[n + 19 :] == -1).all()


def test_a_far_cars_lowest_scan_line_belongs_to_it() -> None:
    """At 40 m a rotating scanner's beams are a few decimetres apart: the car's ground-level
    scan line lies 0.35 m below its body's lowest points. It goes with the car within the
    scanner's angle (0.01 rad: 0.4 m there), not within tyre_radius alone; a road point 1 m
    off stays free, and a near car takes only its tyre_radius."""
    far = box_surface((40, 0, 0.9), (4.0, 1.8, 1.0), step=0.1)
    scan_line = np.array([[39.0, 0.0, 0.05], [41.0, 0.0, 0.05]])  # 0.35 m below the body
    road = np.array([[40.0, 1.9, 0.0]])
    near = box_surface((8, 0, 0.9), (4.0, 1.8, 1.0), step=0.1)
    near_line = np.array([[8.0, 0.0, 0.05]])  # 0.35 m below, at 8 m: the road's
    xyz = np.r_[far, scan_line, road, near, near_line]
    n, m = len(far), len(near)
    label = np.r_[np.zeros(n), -np.ones(3), np.ones(m), -np.ones(1)].astype(np.int32)
    near_ground = np.r_[np.zeros(n, bool), np.ones(3, bool), np.zeros(m, bool), [True]]
    trackable = np.array([True, True])
    plain = object_hosts(xyz, label, trackable, near_ground, 0.2, 0.8)
    angled = object_hosts(xyz, label, trackable, near_ground, 0.2, 0.8, ground_angle=0.01)
    assert (plain[n : n + 3] == -1).all()
    assert (angled[n : n + 2] == 0).all() and angled[n + 2] == -1
    assert angled[-1] == -1


def test_a_parked_van_keeps_its_grazed_points_but_not_a_walker_merged_into_it() -> None:
    """A parked van followed over six frames, 2 % of its points free: DUFOMap's grazing rays
    flag a thin band along its far side, and those stay (keep_static_tracks). In one frame a
    person walking past merged into its cluster: a compact group of free points, which goes."""
    van = box_surface((12, 4, 1.2), (5.0, 2.0, 2.2), step=0.1)
    n = len(van)
    band = np.flatnonzero((np.abs(van[:, 1] - 5.0) < 0.01) & (van[:, 2] > 1.9))[: n // 50]
    walker = box((12.5, 2.7, 0.9), (0.4, 0.4, 1.6), 60)  # merged at the van's side
    evidence, observations = [], []
    for i in range(6):
        xyz = np.r_[van, walker] if i == 3 else van
        free = np.zeros(len(xyz), bool)
        free[band] = True
        if i == 3:
            free[n:] = True
        cluster = np.zeros(len(xyz), np.int32)
        evidence.append(
            FrameEvidence(
                in_view=np.zeros(len(xyz), bool), camera_removed=np.zeros(len(xyz), bool),
                padded=np.zeros(len(xyz), bool), cluster=cluster, free=free,
                free_group=free_groups(xyz, cluster, free, 20, 0.4),
            )
        )  # fmt: skip
        observations.append(
            Observation(
                frame=i, time=0.1 * i, centroids=xyz.mean(axis=0, keepdims=True),
                points=np.array([float(len(xyz))]), camera_class=np.zeros(1, np.uint8),
                free_points=np.array([float(free.sum())]), trackable=np.ones(1, bool),
            )
        )  # fmt: skip
    assert evidence[3].free_group[n:].all()  # the walker: one compact group
    assert not evidence[3].free_group[:n].any() and not evidence[0].free_group.any()  # 5 m
    tracks = track_clusters(observations, gate=2.5, min_frames=3)
    removed = fuse(evidence, tracks, ClutterConfig(mode="dynamic"))
    assert not any(removed[i].any() for i in (0, 1, 2, 4, 5))
    assert removed[3][n:].all() and not removed[3][:n].any()
    unkept = fuse(evidence, tracks, ClutterConfig(mode="dynamic", keep_static_tracks=False))
    assert unkept[0][band].all()
