"""Streets built around one situation that clutter removal finds hard (issue 19): what failed
on real streets the pipeline was never tuned on, made reproducible with exact ground truth.

Each is a town street (buildings, trees, lamps, signs, parked cars) without the presets' usual
traffic, plus the situation's actors; the drive starts at station 0 and the street reaches
`REACH_BEHIND` metres behind it, so cars far behind the survey vehicle stand on ground:
- `receding`: cars driving away behind the survey vehicle, outside the camera's view: two in the
  oncoming lanes that passed it before the drive starts (24-36 m back, then receding at both
  speeds) and one in the lane beside it, slower, falling behind from 27-32 m;
- `approaching`: cars closing in from behind, outside the view: one in the lane beside the
  survey vehicle 6-9 m/s faster from 26-30 m back, one in its own lane 3-5 m/s faster from
  28-34 m back;
- `walkers`: people walking along the shop fronts of both sidewalks, parallel to the drive, at
  1-1.5 m/s, both ways (drive it slowly, as in town traffic, and they stay at one distance);
- `market`: market stalls under awnings along the right sidewalk, crates, a bike rack with
  parked bicycles, a shop canopy on the left, people standing and strolling under them (clutter
  mode: the people and the bicycles are clutter; the stalls, crates, rack and canopy are not);
- `shadow`: parked vehicles a camera barely sees: cars in deep shadow (`Body.shade`), a trailer
  and site machines (an excavator, a road roller; SemanticKITTI other-vehicle), between
  ordinary parked cars;
- `parked_rows`: parked vehicles of every length nose to tail on both sides, some closer than a
  scanner resolves (a row that clusters as one object): buses, lorries, caravans (SemanticKITTI
  other-vehicle; no Cityscapes class), vans, cars and trailers.
"""

from __future__ import annotations

import numpy as np

from app.core.labels import Semantic
from app.simulate import objects
from app.simulate.layout import (
    ARTERIAL,
    CURB_HEIGHT,
    HALO_MARGIN,
    URBAN,
    VEHICLE_MAKERS,
    CrossSection,
    Drive,
    SceneBuilder,
    add_vehicle,
    building_rows,
    ground_strips,
    lane_markings,
    parked_vehicles,
    roadside_vegetation,
    street_furniture,
    survey_drive,
)
from app.simulate.road import Centerline, RoadProfile
from app.simulate.scene import Scene
from app.simulate.traffic import SpeedPlan, path_motion

SITUATIONS = ("receding", "approaching", "walkers", "market", "shadow", "parked_rows")
REACH_BEHIND = 70.0  # metres of street modelled behind the drive's start
REACH_AHEAD = 40.0  # and beyond its end
DEEP_SHADOW = 0.1  # camera brightness of a vehicle in deep shadow


def build_situation(
    situation: str,
    length: float,
    rng: np.random.Generator,
    drive_speed: float | None = None,
    vegetation: bool = False,
) -> Scene:
    """The street of `situation` (module doc), `length` metres driven, drawn from `rng`;
    `vegetation` adds hedges and bushes, drawn last (`layout.roadside_vegetation`)."""
    if situation not in SITUATIONS:
        raise ValueError(f"unknown situation {situation!r}: {', '.join(SITUATIONS)}")
    profile = RoadProfile(length, curves=(), grade=rng.uniform(-0.02, 0.02), hill=0.0)
    centerline = Centerline.from_profile(profile, margin=REACH_BEHIND + 10.0)
    b = SceneBuilder(centerline, rng)
    cs = ARTERIAL if situation in ("receding", "approaching") else URBAN
    s0, s1 = -REACH_BEHIND, length + REACH_AHEAD
    ground_strips(b, cs, s0, s1, sidewalk=True)
    lane_markings(b, cs, s0, s1, dashed=[0.0] if cs is URBAN else [3.5, 0.0, -3.5])
    building_rows(b, cs, s0, s1)
    street_furniture(b, cs, s0, s1, dz=CURB_HEIGHT)
    parking = (cs.lane_edge + cs.outer_edge) / 2
    if situation not in ("market", "shadow", "parked_rows"):  # the stalls face the right curb
        parked_vehicles(b, -parking, s0, s1, 0.0, fill=0.4)
    if situation not in ("shadow", "parked_rows"):
        parked_vehicles(b, parking, s0, s1, np.pi, fill=0.4)
    speed = rng.uniform(8.0, 11.0) if drive_speed is None else drive_speed
    drive, vehicle = survey_drive(b, cs.lane_centres[0], speed, length)
    ACTORS[situation](b, drive, cs, length)
    if vegetation:
        roadside_vegetation(b, cs, s0, s1, dz=CURB_HEIGHT)
    return Scene(
        name=f"{situation}-{length:g}m",
        seed=-1,
        bodies=b.bodies,
        centerline=centerline.xyz,
        vehicle_path=vehicle,
        duration=drive.duration,
    )


def receding(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    rng = b.rng
    outer, inner = cs.lane_centres  # the survey direction's lanes (right side, negative)
    add_vehicle(b, drive, "car", -inner, -1, rng.uniform(9.0, 13.0), -rng.uniform(24.0, 30.0))
    add_vehicle(b, drive, "van", -outer, -1, rng.uniform(8.0, 12.0), -rng.uniform(30.0, 36.0))
    slower = max(drive.speed - rng.uniform(3.0, 5.0), 2.0)
    add_vehicle(b, drive, "car", inner, 1, slower, -rng.uniform(27.0, 32.0))


def approaching(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    rng = b.rng
    outer, inner = cs.lane_centres
    add_vehicle(b, drive, "car", inner, 1, drive.speed + rng.uniform(6.0, 9.0),
                -rng.uniform(26.0, 30.0))  # fmt: skip
    add_vehicle(b, drive, "car", outer, 1, drive.speed + rng.uniform(3.0, 5.0),
                -rng.uniform(28.0, 34.0))  # fmt: skip


def _sidewalk_path(b: SceneBuilder, lateral: float, s_from: float, s_to: float) -> np.ndarray:
    """A walking line on the sidewalk (on its surface, the curb's height above the road)."""
    stations = np.linspace(s_from, s_to, max(int(abs(s_to - s_from) / 0.5), 2) + 1)
    return b.centerline.offset_points(stations, np.full(len(stations), lateral), CURB_HEIGHT)


def _walker(b: SceneBuilder, drive: Drive, lateral: float, station: float, direction: int,
            speed: float) -> None:  # fmt: skip
    """A person walking along the street from `station` at t = 0."""
    reach = speed * (drive.duration + 2.0) + 5.0
    path = _sidewalk_path(b, lateral, station, station + direction * reach)
    motion = path_motion(path, SpeedPlan(speed), 0.0, drive.duration + 1.0)
    b.thing("pedestrian", [(objects.pedestrian(b.rng).mesh, Semantic.PERSON)], motion)


def walkers(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    rng = b.rng
    walk = cs.sidewalk_edge - cs.outer_edge
    for k in range(6):
        side = 1.0 if k % 2 else -1.0
        lateral = side * (cs.outer_edge + rng.uniform(0.25, 0.85) * walk)
        station = rng.uniform(-12.0, length + 25.0)
        direction = 1 if rng.random() < 0.5 else -1
        _walker(b, drive, lateral, station, direction, rng.uniform(1.0, 1.5))


def _standing(b: SceneBuilder, station: float, lateral: float, yaw: float) -> None:
    person = objects.pedestrian(b.rng)
    b.thing("standing-person", [(b.place(person.mesh, station, lateral, yaw, CURB_HEIGHT),
                                 Semantic.PERSON)])  # fmt: skip


def market(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    rng = b.rng
    facing_road = np.pi  # right side: the objects' local -y turned towards the road (+lateral)
    back = -(cs.sidewalk_edge - 0.7)  # the stalls' backs near the building line
    s = rng.uniform(-5.0, 5.0)
    while s < length + 20.0:
        stall = objects.market_stall(rng)
        width, reach = stall.params["width"], stall.params["reach"]
        mesh = b.place(stall.mesh, s + width / 2, back, facing_road, CURB_HEIGHT)
        b.thing("market-stall", [(mesh, Semantic.OTHER_STRUCTURE)])
        for _ in range(int(rng.integers(1, 3))):  # customers under the awning
            under = back + rng.uniform(1.0, max(reach - 0.3, 1.1))
            _standing(b, s + rng.uniform(0.3, width - 0.3), under, rng.uniform(-np.pi, np.pi))
        stack = objects.crates(rng)
        crate_at = b.place(stack.mesh, s + width + 0.4, back, facing_road, CURB_HEIGHT)
        b.thing("crates", [(crate_at, Semantic.OTHER_STRUCTURE)])
        s += width + rng.uniform(1.5, 3.0)
    # a bike rack at the curb with bicycles parked along it
    hoops = int(rng.integers(4, 7))
    rack_at = rng.uniform(0.0, max(length, 5.0))
    curb_side = -(cs.outer_edge + 0.8)
    rack = b.place(objects.bike_rack(rng, hoops).mesh, rack_at, curb_side, 0.0, CURB_HEIGHT)
    b.thing("bike-rack", [(rack, Semantic.OTHER_STRUCTURE)])
    for k in range(hoops):
        if rng.random() < 0.7:
            bike = objects.cyclist(rng).meshes["bicycle"]
            at = b.place(bike, rack_at + k * 1.0 + 0.3, curb_side, np.pi / 2, CURB_HEIGHT)
            b.thing("parked-bicycle", [(at, Semantic.BICYCLE)])
    # a shop canopy over the left sidewalk, people under it
    span = rng.uniform(6.0, 10.0)
    start = rng.uniform(0.0, max(length, 5.0))
    shade = objects.canopy(rng, span)
    wall = cs.sidewalk_edge
    b.thing("canopy", [(b.place(shade.mesh, start + span / 2, wall, 0.0, CURB_HEIGHT),
                        Semantic.BUILDING)])  # fmt: skip
    _standing(b, start + rng.uniform(1.0, span - 1.0), wall - 1.0, rng.uniform(-np.pi, np.pi))
    _walker(b, drive, wall - rng.uniform(0.6, 1.2), start, 1, rng.uniform(0.6, 1.0))


def shadow(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    rng = b.rng
    makers = {"trailer": objects.trailer, "excavator": objects.excavator,
              "roller": objects.road_roller}  # fmt: skip
    parking = (cs.lane_edge + cs.outer_edge) / 2
    for side, facing in ((-1.0, 0.0), (1.0, np.pi)):
        s = -REACH_BEHIND + rng.uniform(0.0, 3.0)
        while s < length + REACH_AHEAD - 6.0:
            draw = rng.random()
            if draw < 0.35:  # a site machine or a trailer, in the shadow or not
                kind = str(rng.choice(list(makers)))
                vehicle = makers[kind](rng)
                semantic, name = Semantic.OTHER_VEHICLE, kind
            else:
                kind = "van" if rng.random() < 0.2 else "car"
                maker, semantic = VEHICLE_MAKERS[kind]
                vehicle, name = maker(rng), f"parked-{kind}"
            dark = rng.random() < 0.5
            mesh = b.place(vehicle.mesh, s + vehicle.size[0] / 2, side * parking, facing)
            b.thing(name, [(mesh, semantic)], halo=HALO_MARGIN,
                    shade=DEEP_SHADOW if dark else 1.0)  # fmt: skip
            s += vehicle.size[0] + rng.uniform(0.8, 2.5)


# parked_rows: (maker, SemanticKITTI class, name, share of the draws)
ROW_VEHICLES = (
    (objects.bus, Semantic.BUS, "parked-bus", 0.15),
    (objects.truck, Semantic.TRUCK, "parked-truck", 0.15),
    (objects.caravan, Semantic.OTHER_VEHICLE, "caravan", 0.2),
    (objects.van, Semantic.OTHER_VEHICLE, "parked-van", 0.15),
    (objects.car, Semantic.CAR, "parked-car", 0.25),
    (objects.trailer, Semantic.OTHER_VEHICLE, "trailer", 0.1),
)
TOUCHING_GAP = 0.15  # metres: closer than the clusters' voxel, two vehicles cluster as one


def parked_rows(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    rng = b.rng
    share = np.array([v[3] for v in ROW_VEHICLES])
    parking = (cs.lane_edge + cs.outer_edge) / 2
    for side, facing in ((-1.0, 0.0), (1.0, np.pi)):
        s = -REACH_BEHIND + rng.uniform(0.0, 3.0)
        while s < length + REACH_AHEAD - 13.0:
            maker, semantic, name, _ = ROW_VEHICLES[rng.choice(len(share), p=share / share.sum())]
            vehicle = maker(rng)
            mesh = b.place(vehicle.mesh, s + vehicle.size[0] / 2, side * parking, facing)
            b.thing(name, [(mesh, semantic)], halo=HALO_MARGIN)
            touching = rng.random() < 0.3
            s += vehicle.size[0] + (TOUCHING_GAP if touching else rng.uniform(0.8, 3.0))


ACTORS = {"receding": receding, "approaching": approaching, "walkers": walkers,
          "market": market, "shadow": shadow, "parked_rows": parked_rows}  # fmt: skip
