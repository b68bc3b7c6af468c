"""Street presets: where the road, sidewalks, buildings, trees, poles, signs, parked vehicles,
guardrails and the traffic go, drawn deterministically from one random generator.

Cross-sections are given as lateral offsets from the road centreline (left of the direction of
travel positive); the survey vehicle drives in the right-hand lane in +s. The scene reaches 30 m
beyond both ends of the driven stretch so the scanner sees a complete street everywhere.

- `urban`: one lane each way, parking lanes, curbs, 3.5 m sidewalks, building rows with
  recesses, street trees, lamps, signs; a pipe guardrail along the right sidewalk and a beam
  guardrail along the left one; cars, vans, a truck, a cyclist and pedestrians (one crossing).
- `highway`: two lanes each way, shoulders, beam guardrails on both edges and in the median,
  grass and trees beyond; fast cars and trucks in both directions, an overtaking car.
- `mixed`: an arterial with two lanes each way, buildings along its first half only, guardrails
  of both kinds, cars overtaking the survey vehicle (long phantoms), a traffic light where
  oncoming traffic stops and starts again, and a tram.
- `interchange`: the highway at an exit: an auxiliary lane on the right that leaves as a ramp
  curving away (its guardrail turns away from the trajectory, seen at ever more grazing
  angles), the edge guardrail resuming at the gore, often a second guardrail along the ramp's
  inner edge facing away from the survey, and in the median a concrete New Jersey barrier
  (two drives in three; else the beam guardrail): a guardrail-shaped object the classifier
  must call other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.core.labels import Semantic
from app.simulate import objects
from app.simulate.colors import COLORS
from app.simulate.guardrails import beam_guardrail, pipe_guardrail
from app.simulate.meshes import strip
from app.simulate.road import Centerline, RoadProfile, bends
from app.simulate.scene import Body, Mesh, Motion, Scene
from app.simulate.traffic import SpeedPlan, path_motion

PRESETS = ("urban", "highway", "mixed", "interchange")
SCENE_MARGIN = 30.0  # metres of street modelled beyond both ends of the drive
CURB_HEIGHT = 0.15
HALO_MARGIN = 0.2  # metres: laser-bounce halo around vehicle bodies (clutter paper, Fig. 6)

REFLECTIVITY = {
    Semantic.ROAD: 0.15,
    Semantic.PARKING: 0.18,
    Semantic.LANE_MARKING: 0.8,
    Semantic.SIDEWALK: 0.3,
    Semantic.OTHER_GROUND: 0.25,
    Semantic.TERRAIN: 0.35,
    Semantic.BUILDING: 0.35,
    Semantic.VEGETATION: 0.45,
    Semantic.TRUNK: 0.25,
    Semantic.POLE: 0.5,
    Semantic.TRAFFIC_SIGN: 0.9,  # retro-reflective
    Semantic.FENCE: 0.6,
    Semantic.OTHER_STRUCTURE: 0.4,
}
VEHICLE_MAKERS: dict[str, tuple[Callable, int]] = {
    "car": (objects.car, Semantic.CAR),
    "van": (objects.van, Semantic.OTHER_VEHICLE),
    "truck": (objects.truck, Semantic.TRUCK),
    "bus": (objects.bus, Semantic.BUS),
    "tram": (objects.tram, Semantic.ON_RAILS),
}


@dataclass(frozen=True)
class CrossSection:
    """Lateral layout of one side of the street (right side: negated offsets)."""

    lane_edge: float  # outer edge of the driving lanes
    outer_edge: float  # curb line / road edge (parking lane or shoulder in between)
    sidewalk_edge: float  # building line / end of sidewalk or verge
    back_edge: float  # end of the modelled ground behind
    lane_centres: tuple[float, ...]  # lanes of the survey direction (right side, negative)


URBAN = CrossSection(3.5, 5.7, 9.2, 25.0, (-1.75,))
ARTERIAL = CrossSection(7.0, 9.2, 12.7, 28.0, (-5.25, -1.75))  # two lanes each way (mixed)
HIGHWAY = CrossSection(7.75, 10.25, 40.0, 40.0, (-2.0, -5.875))


class SceneBuilder:
    """Collects bodies with running instance ids."""

    def __init__(self, centerline: Centerline, rng: np.random.Generator):
        self.centerline = centerline
        self.rng = rng
        self.bodies: list[Body] = []
        self.guardrails: list[dict] = []
        self._next_instance = 1

    def new_instance(self) -> int:
        self._next_instance += 1
        return self._next_instance - 1

    def stuff(self, name: str, mesh: Mesh, semantic: int) -> None:
        """Uncountable surfaces (road, sidewalk, buildings): instance 0."""
        self.bodies.append(Body(name, mesh, semantic, 0, COLORS[semantic], REFLECTIVITY[semantic]))

    def thing(
        self,
        name: str,
        pieces: list[tuple[Mesh, int]],
        motion: Motion | None = None,
        halo: float = 0.0,
        reflectivity: float | None = None,
        guardrail: int = -1,
        shade: float = 1.0,
    ) -> int:
        """A countable object of one or more (mesh, class) pieces sharing one instance id."""
        instance = self.new_instance()
        for mesh, semantic in pieces:
            refl = REFLECTIVITY.get(semantic, 0.4) if reflectivity is None else reflectivity
            body = Body(name, mesh, semantic, instance, COLORS[semantic], refl, motion, guardrail,
                        halo, shade)  # fmt: skip
            self.bodies.append(body)
        return instance

    def pose(self, station: float, lateral: float, yaw: float = 0.0, dz: float = 0.0):
        """(R, t) placing a local frame at (station, lateral), heading + yaw, on the slope."""
        xyz = self.centerline.offset_points(np.array([station]), np.array([lateral]), dz)
        _, heading, slope = self.centerline.at(np.array([station]))
        pitch = np.arctan(slope) * np.cos(yaw)
        T = Motion(np.zeros(1), xyz, heading + yaw, pitch).poses(np.zeros(1))[0]
        return T[:3, :3], T[:3, 3]

    def place(self, mesh: Mesh, station, lateral, yaw=0.0, dz=0.0) -> Mesh:
        R, t = self.pose(station, lateral, yaw, dz)
        return mesh.transformed(R, t)


# ------------------------------------------------------------------------------ static parts


def ground_strips(b: SceneBuilder, cs: CrossSection, s0: float, s1: float, sidewalk: bool):
    """Road, parking lanes / shoulders, curbs, sidewalks (or verges) and the ground behind."""
    line = b.centerline.line
    b.stuff("road", strip(line(cs.lane_edge, s0, s1), line(-cs.lane_edge, s0, s1)), Semantic.ROAD)
    outer_class = Semantic.PARKING if sidewalk else Semantic.ROAD
    for side in (1.0, -1.0):
        lane, outer = side * cs.lane_edge, side * cs.outer_edge
        b.stuff("road-edge", strip(line(lane, s0, s1), line(outer, s0, s1)), outer_class)
        if sidewalk:
            top = CURB_HEIGHT
            curb = strip(line(outer, s0, s1), line(outer, s0, s1, dz=top))
            b.stuff("curb", curb, Semantic.SIDEWALK)
            walk = strip(line(outer, s0, s1, dz=top), line(side * cs.sidewalk_edge, s0, s1, dz=top))
            b.stuff("sidewalk", walk, Semantic.SIDEWALK)
            back = strip(
                line(side * cs.sidewalk_edge, s0, s1, dz=top),
                line(side * cs.back_edge, s0, s1, dz=top),
            )
            b.stuff("backyard", back, Semantic.OTHER_GROUND)
        else:
            verge = strip(line(outer, s0, s1), line(side * cs.sidewalk_edge, s0, s1, dz=-0.2))
            b.stuff("verge", verge, Semantic.TERRAIN)


def lane_markings(b: SceneBuilder, cs: CrossSection, s0: float, s1: float, dashed: list[float]):
    """Solid edge lines and dashed lane lines (3 m dash, 6 m gap), 12-15 cm wide, 3 mm proud."""
    line = b.centerline.line
    pieces = []
    for edge in (cs.lane_edge - 0.2, -(cs.lane_edge - 0.2)):
        pieces.append(
            strip(line(edge + 0.075, s0, s1, dz=0.003), line(edge - 0.075, s0, s1, dz=0.003))
        )
    for lateral in dashed:
        for start in np.arange(s0, s1 - 3.0, 9.0):
            pieces.append(
                strip(
                    line(lateral + 0.06, start, start + 3.0, dz=0.003),
                    line(lateral - 0.06, start, start + 3.0, dz=0.003),
                )
            )
    b.stuff("lane-markings", Mesh.merge(pieces), Semantic.LANE_MARKING)


def building_rows(b: SceneBuilder, cs: CrossSection, s0: float, s1: float) -> None:
    for side in (1.0, -1.0):
        baseline = b.centerline.line(side * cs.sidewalk_edge, s0, s1, dz=CURB_HEIGHT)
        if side > 0:  # facade() wants the road on the left of the baseline's direction
            baseline = baseline[::-1]
        mesh = objects.facade(baseline, b.rng.uniform(10.0, 20.0), b.rng)
        b.stuff("buildings", mesh, Semantic.BUILDING)


def street_furniture(
    b: SceneBuilder, cs: CrossSection, s0: float, s1: float, dz: float, sides=(1.0, -1.0)
) -> None:
    """Trees, lamps and signs along both sides (or the `sides` given: +1 left, -1 right)."""
    for side in sides:
        # road side of a roadside object is its local -y: turn it to face the road
        facing_road = np.pi if side < 0 else 0.0
        s = s0 + b.rng.uniform(2.0, 8.0)
        while s < s1:
            tree = objects.tree(b.rng)
            lateral = side * (cs.outer_edge + 0.6 * (cs.sidewalk_edge - cs.outer_edge))
            b.thing(
                "tree",
                [
                    (b.place(tree.meshes["trunk"], s, lateral, dz=dz), Semantic.TRUNK),
                    (b.place(tree.meshes["crown"], s, lateral, dz=dz), Semantic.VEGETATION),
                ],
            )
            s += b.rng.uniform(10.0, 18.0)
        s = s0 + b.rng.uniform(8.0, 14.0)
        while s < s1:
            lamp = objects.pole(b.rng)
            lateral = side * (cs.outer_edge + 0.9)  # behind a guardrail on the curb line
            b.thing("lamp", [(b.place(lamp.mesh, s, lateral, facing_road, dz), Semantic.POLE)])
            s += b.rng.uniform(22.0, 32.0)
        for s in b.rng.uniform(s0 + 5.0, s1 - 5.0, size=int(b.rng.integers(1, 3))):
            sign = objects.sign(b.rng)
            yaw = -np.pi / 2 if side < 0 else np.pi / 2  # face the traffic that approaches
            lateral = side * (cs.outer_edge + 1.2)
            b.thing(
                "sign",
                [
                    (b.place(sign.meshes["pole"], s, lateral, yaw, dz), Semantic.POLE),
                    (b.place(sign.meshes["plate"], s, lateral, yaw, dz), Semantic.TRAFFIC_SIGN),
                ],
            )


def roadside_vegetation(b: SceneBuilder, cs: CrossSection, s0: float, s1: float, dz: float) -> None:
    """Hedges and bushes in front of the buildings on both sides, with gaps, and now and then a
    bush on the verge between the trees: the scattered, car-sized leaf masses that real streets
    have and a smooth crown does not show (`objects.bush`, `objects.hedge`)."""
    for side in (1.0, -1.0):
        s = s0 + b.rng.uniform(0.0, 6.0)
        while s < s1:
            if b.rng.random() < 0.5:
                length = b.rng.uniform(2.0, 8.0)
                plant = objects.hedge(b.rng, length)
            else:
                plant = objects.bush(b.rng)
                length = plant.size[0]
            depth = plant.size[1]
            lateral = side * (cs.sidewalk_edge - 0.5 * depth - b.rng.uniform(0.1, 0.4))
            station = s + 0.5 * length
            yaw = b.rng.uniform(-0.2, 0.2) if plant.kind == "bush" else 0.0
            placed = b.place(plant.meshes["foliage"], station, lateral, yaw, dz)
            b.thing(plant.kind, [(placed, Semantic.VEGETATION)])
            s += length + b.rng.uniform(1.0, 10.0)
        for s in b.rng.uniform(s0, s1, size=int(b.rng.integers(1, 4))):
            plant = objects.bush(b.rng)
            lateral = side * (cs.outer_edge + 0.3 * (cs.sidewalk_edge - cs.outer_edge))
            placed = b.place(plant.meshes["foliage"], s, lateral, 0.0, dz)
            b.thing("bush", [(placed, Semantic.VEGETATION)])


def parked_vehicles(
    b: SceneBuilder, lateral: float, s0: float, s1: float, facing: float, fill: float = 0.75
) -> None:
    """Cars and vans parked one behind the other in a parking lane (static short objects)."""
    s = s0 + b.rng.uniform(0.0, 3.0)
    while True:
        kind = "van" if b.rng.random() < 0.2 else "car"
        maker, semantic = VEHICLE_MAKERS[kind]
        vehicle = maker(b.rng)
        length = vehicle.size[0]
        if s + length > s1:
            break
        if b.rng.random() < fill:
            mesh = b.place(vehicle.mesh, s + length / 2, lateral, facing)
            b.thing(f"parked-{kind}", [(mesh, semantic)], halo=HALO_MARGIN)
        s += length + b.rng.uniform(0.8, 2.5)


def add_guardrail(b: SceneBuilder, kind: str, lateral: float, s0: float, s1: float, dz: float):
    """A guardrail on a line parallel to the road; the road is towards the centreline."""
    line = b.centerline.line(lateral, s0, s1, step=0.25, dz=dz)
    add_guardrail_on(b, kind, line, "left" if lateral < 0 else "right")


def add_guardrail_on(b: SceneBuilder, kind: str, line: np.ndarray, road_side: str) -> None:
    """A guardrail along any `line` (K, 3) with its road on `road_side` of the line."""
    make = pipe_guardrail if kind == "pipe" else beam_guardrail
    rail = make(line, b.rng, road_side=road_side)
    index = len(b.guardrails)
    b.guardrails.append(rail.model)
    b.thing(f"guardrail-{kind}", [(rail.mesh, Semantic.FENCE)], guardrail=index)


@dataclass(frozen=True)
class ExitRamp:
    """An exit on the right: an auxiliary lane `width` m wide outside the shoulder edge that,
    from station `start`, swings `shift` m further right over `length` m (a cosine easing) and
    then runs parallel as the ramp."""

    edge: float  # the main road's right edge (positive metres from the centreline)
    width: float
    start: float
    length: float
    shift: float

    def offset(self, s: np.ndarray) -> np.ndarray:
        """Metres the ramp has moved right of the auxiliary lane at stations `s`."""
        u = np.clip((np.asarray(s, dtype=np.float64) - self.start) / self.length, 0.0, 1.0)
        return self.shift * 0.5 * (1.0 - np.cos(np.pi * u))

    def station_at_offset(self, offset: float) -> float:
        """First station where the ramp has moved `offset` m (offset < shift)."""
        u = np.arccos(1.0 - 2.0 * offset / self.shift) / np.pi
        return self.start + float(u) * self.length

    def line(self, b: SceneBuilder, extra: float, s0: float, s1: float, dz: float = 0.0):
        """Polyline at the ramp's inner edge moved `extra` m right, from s0 to s1."""
        stations = np.linspace(s0, s1, max(int(np.ceil((s1 - s0) / 0.25)), 1) + 1)
        lateral = -(self.edge + self.offset(stations) + extra)
        return b.centerline.offset_points(stations, lateral, dz)


def exit_ramp(b: SceneBuilder, cs: CrossSection, s0: float, s1: float, length: float) -> ExitRamp:
    """The ramp's pavement, its outer guardrail, the edge guardrail from the gore on and (one
    in two) a guardrail along the ramp's inner edge from the gore, facing the ramp."""
    rng = b.rng
    ramp = ExitRamp(cs.outer_edge, rng.uniform(3.75, 4.5), rng.uniform(-0.2, 0.5) * length,
                    rng.uniform(50.0, 80.0), rng.uniform(8.0, 12.0))  # fmt: skip
    pavement = strip(ramp.line(b, 0.0, s0, s1, 0.01), ramp.line(b, ramp.width, s0, s1, 0.01))
    b.stuff("ramp", pavement, Semantic.ROAD)
    add_guardrail_on(b, "beam", ramp.line(b, ramp.width + 0.5, s0, s1), "left")
    gore = ramp.station_at_offset(2.5)
    if gore < s1 - 5.0:
        add_guardrail(b, "beam", -(cs.outer_edge + 0.3), gore, s1, dz=0.0)
        if rng.random() < 0.5:
            add_guardrail_on(b, "beam", ramp.line(b, -0.4, gore + 2.0, s1), "right")
    return ramp


# ------------------------------------------------------------------------------ traffic


@dataclass
class Drive:
    """The survey vehicle's drive: speed and duration, to time the traffic around it."""

    speed: float
    duration: float

    def station_at(self, t: float) -> float:
        return self.speed * t


def lane_path(b: SceneBuilder, lateral: float, s_from: float, s_to: float) -> np.ndarray:
    """Polyline along a lane from s_from to s_to (either direction)."""
    n = max(int(abs(s_to - s_from) / 0.5), 2)
    stations = np.linspace(s_from, s_to, n + 1)
    return b.centerline.offset_points(stations, np.full(len(stations), lateral))


def add_vehicle(
    b: SceneBuilder,
    drive: Drive,
    kind: str,
    lateral: float,
    direction: int,
    speed: float,
    start_station: float,
    plan: SpeedPlan | None = None,
) -> None:
    maker, semantic = VEHICLE_MAKERS[kind]
    vehicle = maker(b.rng)
    reach = speed * (drive.duration + 2.0) + 60.0
    path = lane_path(b, lateral, start_station, start_station + direction * reach)
    motion = path_motion(path, plan or SpeedPlan(speed), 0.0, drive.duration + 1.0)
    b.thing(f"moving-{kind}", [(vehicle.mesh, semantic)], motion, halo=HALO_MARGIN)


def meeting_start(drive: Drive, speed: float, meet_time: float, direction: int, gap=0.0) -> float:
    """Start station of a vehicle that is level with the survey vehicle (+gap) at meet_time."""
    return drive.station_at(meet_time) + gap - direction * speed * meet_time


def add_person(b: SceneBuilder, drive: Drive, path: np.ndarray, speed: float, delay: float):
    person = objects.pedestrian(b.rng)
    motion = path_motion(path, SpeedPlan(speed, start_delay=delay), 0.0, drive.duration + 1.0)
    b.thing("pedestrian", [(person.mesh, Semantic.PERSON)], motion)


def add_cyclist(b: SceneBuilder, drive: Drive, lateral: float, speed: float, meet_time: float):
    rider = objects.cyclist(b.rng)
    start = meeting_start(drive, speed, meet_time, 1)
    path = lane_path(b, lateral, start, start + speed * (drive.duration + 2.0) + 20.0)
    motion = path_motion(path, SpeedPlan(speed), 0.0, drive.duration + 1.0)
    b.thing(
        "cyclist",
        [(rider.meshes["bicycle"], Semantic.BICYCLE), (rider.meshes["rider"], Semantic.BICYCLIST)],
        motion,
    )


def urban_traffic(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> None:
    """Oncoming cars and a van, a car ahead, a cyclist being overtaken, pedestrians."""
    rng = b.rng
    meet = np.sort(rng.uniform(0.15, 0.85, size=3)) * drive.duration
    for t_meet, kind in zip(meet, ("car", "car", "van"), strict=True):
        v = rng.uniform(8.0, 13.0)
        add_vehicle(b, drive, kind, -cs.lane_centres[0], -1, v, meeting_start(drive, v, t_meet, -1))
    v_ahead = drive.speed + rng.uniform(-0.5, 1.5)
    add_vehicle(b, drive, "car", cs.lane_centres[0], 1, v_ahead, rng.uniform(12.0, 18.0))
    add_cyclist(b, drive, cs.lane_centres[0] - 1.3, rng.uniform(4.0, 6.0),
                rng.uniform(0.3, 0.7) * drive.duration)  # fmt: skip
    for side in (1.0, -1.0):  # walking along the sidewalks
        lateral = side * (cs.outer_edge + 0.75 * (cs.sidewalk_edge - cs.outer_edge))
        centre = drive.station_at(rng.uniform(0.3, 0.7) * drive.duration)
        direction = 1 if rng.random() < 0.5 else -1
        path = lane_path(b, lateral, centre - direction * 6.0, centre + direction * 40.0)
        add_person(b, drive, path, rng.uniform(1.2, 1.6), 0.0)
    # one pedestrian crossing from the left sidewalk ahead of the survey vehicle
    s_cross = min(length - 5.0, drive.station_at(0.6 * drive.duration) + 10.0)
    path = b.centerline.offset_points(
        np.full(2, s_cross), np.array([cs.outer_edge + 1.0, -(cs.outer_edge + 2.0)])
    )
    add_person(b, drive, path, 1.4, max(0.0, s_cross / drive.speed - 2.5))


def highway_traffic(b: SceneBuilder, drive: Drive, cs: CrossSection) -> None:
    rng = b.rng
    inner, outer = cs.lane_centres
    for t_meet in np.sort(rng.uniform(0.1, 0.9, size=4)) * drive.duration:
        v = rng.uniform(24.0, 33.0)
        kind = "truck" if rng.random() < 0.3 else "car"
        lateral = -inner if kind == "car" else -outer
        add_vehicle(b, drive, kind, lateral, -1, v, meeting_start(drive, v, t_meet, -1))
    v = rng.uniform(27.0, 32.0)  # overtaking in the inner lane
    add_vehicle(b, drive, "car", inner, 1, v, meeting_start(drive, v, 0.5 * drive.duration, 1))
    add_vehicle(b, drive, "truck", outer, 1, drive.speed - 1.0, rng.uniform(25.0, 35.0))
    add_vehicle(b, drive, "car", outer, 1, drive.speed + 0.5, rng.uniform(-30.0, -20.0))


def mixed_traffic(b: SceneBuilder, drive: Drive, cs: CrossSection, length: float) -> tuple:
    """Urban traffic plus cars overtaking the survey vehicle in the inner lane (the long-drawn
    phantoms of the phantom paper: a profile scanner sees an overtaking car for as long as it
    takes to pass), a red light for the oncoming lane and a tram."""
    urban_traffic(b, drive, cs, length)
    rng = b.rng
    inner = cs.lane_centres[1]
    for t_pass, kind in zip(np.sort(rng.uniform(0.2, 0.8, 2)) * drive.duration, ("car", "van"),
                            strict=True):  # fmt: skip
        v = drive.speed + rng.uniform(2.5, 5.0)
        add_vehicle(b, drive, kind, inner, 1, v, meeting_start(drive, v, t_pass, 1))
    s_light = 0.5 * length
    green = rng.uniform(0.5, 0.8) * drive.duration
    oncoming = -cs.lane_centres[0]
    for gap in (8.0, 16.0):  # queue at the light, then accelerate away
        start = s_light + gap + 20.0
        plan = SpeedPlan(rng.uniform(9.0, 12.0), stop_at=20.0, green_at=green)
        add_vehicle(b, drive, "car", oncoming, -1, plan.speed, start, plan)
    v_tram = rng.uniform(8.0, 11.0)
    add_vehicle(b, drive, "tram", -inner, -1, v_tram,
                meeting_start(drive, v_tram, 0.8 * drive.duration, -1, gap=40.0))  # fmt: skip
    signal = objects.pole(b.rng, arm=True)
    light_pole = b.place(signal.mesh, s_light, cs.outer_edge + 0.9, 0.0, CURB_HEIGHT)
    b.thing("traffic-light", [(light_pole, Semantic.POLE)])
    return (0.0, green)


# ------------------------------------------------------------------------------ presets


def survey_drive(b: SceneBuilder, lateral: float, speed: float, length: float) -> tuple:
    duration = length / speed
    path = lane_path(b, lateral, -5.0, length + 40.0)
    start = 5.0 / speed  # the path starts 5 m behind station 0
    motion = path_motion(path, SpeedPlan(speed), -start, duration + 1.0)
    return Drive(speed, duration), motion


def verge(cs: CrossSection) -> CrossSection:
    """Where a highway's trees, lamps and signs stand: beyond its shoulders."""
    return CrossSection(cs.outer_edge, cs.outer_edge + 2.0, 30.0, 40.0, ())


def carriageway(b: SceneBuilder, cs: CrossSection, s0: float, s1: float) -> None:
    """A highway's pavement, shoulders, verges and lane markings."""
    ground_strips(b, cs, s0, s1, sidewalk=False)
    lane_markings(b, cs, s0, s1, dashed=[3.875, -3.875])


def open_highway(b: SceneBuilder, cs: CrossSection, s0: float, s1: float) -> None:
    """The static parts of the `highway` preset (module doc)."""
    carriageway(b, cs, s0, s1)
    for lateral in (-(cs.outer_edge + 0.3), cs.outer_edge + 0.3):
        add_guardrail(b, "beam", lateral, s0, s1, dz=0.0)
    add_guardrail(b, "beam", -0.3, s0, s1, dz=0.0)
    street_furniture(b, verge(cs), s0, s1, dz=-0.1)


def interchange(b: SceneBuilder, cs: CrossSection, s0: float, s1: float, length: float) -> None:
    """The static parts of the `interchange` preset (module doc)."""
    carriageway(b, cs, s0, s1)
    add_guardrail(b, "beam", cs.outer_edge + 0.3, s0, s1, dz=0.0)
    if b.rng.random() < 2.0 / 3.0:
        barrier = objects.median_barrier(b.centerline.line(0.0, s0, s1, step=0.25), b.rng)
        b.thing("median-barrier", [(barrier, Semantic.FENCE)])
    else:
        add_guardrail(b, "beam", -0.3, s0, s1, dz=0.0)
    ramp = exit_ramp(b, cs, s0, s1, length)
    street_furniture(b, verge(cs), s0, s1, dz=-0.1, sides=(1.0,))
    beyond = cs.outer_edge + ramp.width + ramp.shift + 1.5  # past the ramp's guardrail
    street_furniture(b, CrossSection(beyond - 2.0, beyond, beyond + 15.0, 40.0, ()), s0, s1,
                     dz=-0.1, sides=(-1.0,))  # fmt: skip


def build_scene(
    preset: str,
    length: float,
    rng: np.random.Generator,
    drive_speed: float | None = None,
    vegetation: bool = False,
) -> Scene:
    """The street of `preset`, `length` metres, drawn from `rng`. The survey vehicle's speed
    is drawn too; `drive_speed` replaces the drawn value (drawn all the same, so that the rest
    of the street is the seed's). `vegetation` adds hedges and bushes along a town street,
    drawn after everything else (the rest of the street stays the seed's)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown scene preset {preset!r}: {', '.join(PRESETS)}")
    highway = preset in ("highway", "interchange")
    radius = rng.uniform(600.0, 1200.0) if highway else rng.uniform(120.0, 300.0)
    turn = (1 if rng.random() < 0.5 else -1) / radius
    profile = RoadProfile(
        length,
        curves=bends(0.4 * length, 0.9 * length, turn) if rng.random() < 0.7 else (),
        grade=rng.uniform(-0.04, 0.04),
        hill=rng.uniform(-1.0, 1.0),
    )
    centerline = Centerline.from_profile(profile, margin=SCENE_MARGIN + 10.0)
    b = SceneBuilder(centerline, rng)
    s0, s1 = -SCENE_MARGIN, length + SCENE_MARGIN
    light = None
    if highway:
        cs = HIGHWAY
        if preset == "interchange":
            interchange(b, cs, s0, s1, length)
        else:
            open_highway(b, cs, s0, s1)
        speed = rng.uniform(20.0, 25.0)
        speed = speed if drive_speed is None else drive_speed
        drive, vehicle = survey_drive(b, cs.lane_centres[1], speed, length)
        highway_traffic(b, drive, cs)
    else:
        cs = URBAN if preset == "urban" else ARTERIAL
        ground_strips(b, cs, s0, s1, sidewalk=True)
        lane_markings(b, cs, s0, s1, dashed=[0.0] if preset == "urban" else [3.5, 0.0, -3.5])
        built_end = s1 if preset == "urban" else 0.5 * length
        building_rows(b, cs, s0, built_end)
        street_furniture(b, cs, s0, s1, dz=CURB_HEIGHT)
        rail_right = (0.2 * length, 0.6 * length)
        rail_left = (0.45 * length, 0.85 * length) if preset == "urban" else (0.5 * length, s1)
        add_guardrail(b, "pipe", -(cs.outer_edge + 0.4), *rail_right, dz=CURB_HEIGHT)
        add_guardrail(b, "beam", cs.outer_edge + 0.4, *rail_left, dz=CURB_HEIGHT)
        parking = -(cs.lane_edge + cs.outer_edge) / 2
        parked_vehicles(b, parking, s0, rail_right[0] - 1.0, 0.0)
        parked_vehicles(b, parking, rail_right[1] + 1.0, s1, 0.0)
        parked_vehicles(b, -parking, s0, rail_left[0] - 1.0, np.pi)
        parked_vehicles(b, -parking, rail_left[1] + 1.0, s1, np.pi)
        speed = rng.uniform(8.0, 11.0)
        speed = speed if drive_speed is None else drive_speed
        drive, vehicle = survey_drive(b, cs.lane_centres[0], speed, length)
        if preset == "mixed":
            light = mixed_traffic(b, drive, cs, length)
        else:
            urban_traffic(b, drive, cs, length)
        if vegetation:
            roadside_vegetation(b, cs, s0, s1, dz=CURB_HEIGHT)
    return Scene(
        name=f"{preset}-{length:g}m",
        seed=-1,  # set by the caller that knows the seed (survey.rebuild_scene)
        bodies=b.bodies,
        centerline=centerline.xyz,
        vehicle_path=vehicle,
        duration=drive.duration,
        guardrails=b.guardrails,
        light_stop=light,
    )
