"""Street objects as meshes in their local frame, sizes drawn from realistic ranges.

Local frame: x forward (vehicles, people and bicycles face +x), y left, z up, metres; the
origin is the centre of the footprint on the ground (vehicles, people, cyclists) or the foot of
the pole / trunk (poles, signs, trees), and every object stands on z = 0 (its lowest vertex).
Roadside objects (`pole`, `sign`) turn to the road along local -y: a lamp arm reaches out along
-y and a sign's face (plate normal) points along -y; place them with the yaw that turns -y
towards the viewers they address.

Objects that the ground truth labels in pieces keep them apart in `StreetObject.meshes`
(a cyclist's "bicycle" and "rider", a tree's "trunk" and "crown", a sign's "pole" and "plate");
`facade` builds a row of buildings in world coordinates along a building line.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.simulate.meshes import (
    box,
    cylinder,
    ellipsoid,
    extrude_polygon,
    foliage,
    sweep_profile,
    tube,
)
from app.simulate.scene import Mesh


@dataclass
class StreetObject:
    """One object: named meshes (local frame), bounding-box size and the drawn parameters."""

    kind: str
    meshes: dict[str, Mesh]
    size: tuple[float, float, float]  # extent along x (length), y (width), z (height)
    params: dict[str, float] = field(default_factory=dict)

    @property
    def mesh(self) -> Mesh:
        """All pieces in one mesh."""
        return Mesh.merge(list(self.meshes.values()))


def _finish(kind: str, meshes: dict[str, Mesh], params: dict[str, float]) -> StreetObject:
    """Stand the object on z = 0 and measure its bounding box."""
    V = np.concatenate([m.vertices for m in meshes.values()])
    lift = -V[:, 2].min()
    for m in meshes.values():
        m.vertices[:, 2] += lift
    V[:, 2] += lift
    ext = V.max(0) - V.min(0)
    return StreetObject(kind, meshes, (float(ext[0]), float(ext[1]), float(ext[2])), params)


def _side_profile(poly_xz: np.ndarray | list, width: float, y0: float = 0.0) -> Mesh:
    """A side outline (x, z), counter-clockwise, extruded across y over `width` about `y0`."""
    m = extrude_polygon(np.asarray(poly_xz, dtype=np.float64), -0.5 * width, 0.5 * width)
    V = m.vertices
    m.vertices = np.column_stack([V[:, 0], y0 - V[:, 2], V[:, 1]])  # rotation about x by +90 deg
    return m


def _wheels(xs: list[float], width_body: float, radius: float, tyre: float) -> list[Mesh]:
    """A pair of wheels (cylinders along y, flush inside the body's sides) per axle x."""
    out = []
    for x in xs:
        for sgn in (-1.0, 1.0):
            y_out = sgn * (0.5 * width_body - 0.02)
            out.append(cylinder((x, y_out - sgn * tyre, radius), (x, y_out, radius), radius, 16))
    return out


# ----------------------------------------------------------------------------- vehicles


def car(rng: np.random.Generator) -> StreetObject:
    """Passenger car: lower body box, narrower cabin with sloped windscreen and rear window,
    four wheels. Length 4.0-4.8, width 1.7-1.9, height 1.4-1.6 m."""
    L, W, H = rng.uniform(4.0, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.6)
    clear, r = rng.uniform(0.15, 0.2), rng.uniform(0.29, 0.33)
    belt = rng.uniform(0.55, 0.62) * H
    Wc = W - rng.uniform(0.12, 0.2)
    xb0, xb1 = -0.5 * L + rng.uniform(0.25, 0.5), 0.5 * L - rng.uniform(1.1, 1.4)
    xt0 = xb0 + rng.uniform(0.2, 0.5)
    xt1 = max(xb1 - rng.uniform(0.7, 0.9), xt0 + 0.8)
    body = box((L, W, belt - clear), (0.0, 0.0, 0.5 * (belt + clear)))
    cabin = _side_profile([(xb0, belt - 0.01), (xb1, belt - 0.01), (xt1, H), (xt0, H)], Wc)
    axle = 0.5 * L - rng.uniform(0.75, 0.9)
    parts = [body, cabin, *_wheels([axle, -axle], W, r, 0.2)]
    return _finish("car", {"body": Mesh.merge(parts)}, {"length": L, "width": W, "height": H})


def van(rng: np.random.Generator) -> StreetObject:
    """Van: one tall box with a short sloped bonnet and windscreen, four wheels.
    4.8-5.5 x 1.9-2.1 x 1.9-2.4 m."""
    L, W, H = rng.uniform(4.8, 5.5), rng.uniform(1.9, 2.1), rng.uniform(1.9, 2.4)
    c, r = rng.uniform(0.18, 0.22), rng.uniform(0.32, 0.36)
    hood_z, hood, wind = rng.uniform(0.95, 1.1), rng.uniform(0.35, 0.6), rng.uniform(0.5, 0.7)
    outline = [
        (-0.5 * L, c),
        (0.5 * L, c),
        (0.5 * L, hood_z),
        (0.5 * L - hood, hood_z + 0.05),
        (0.5 * L - hood - wind, H),
        (-0.5 * L, H),
    ]
    axle = 0.5 * L - rng.uniform(0.8, 1.0)
    parts = [_side_profile(outline, W), *_wheels([axle, -axle + 0.1], W, r, 0.22)]
    return _finish("van", {"body": Mesh.merge(parts)}, {"length": L, "width": W, "height": H})


def truck(rng: np.random.Generator) -> StreetObject:
    """Lorry: cab at the front, a taller cargo box behind it on a chassis, two or three axles.
    7-10 x 2.4-2.5 x 3.0-3.6 m."""
    L, W, H = rng.uniform(7.0, 10.0), rng.uniform(2.4, 2.5), rng.uniform(3.0, 3.6)
    r = rng.uniform(0.48, 0.52)
    cab_len, cab_h = rng.uniform(1.8, 2.3), H - rng.uniform(0.2, 0.6)
    xc = 0.5 * L - cab_len
    floor = rng.uniform(0.95, 1.15)
    cab = _side_profile(
        [(xc, 0.45), (0.5 * L, 0.45), (0.5 * L, cab_h - 0.3), (0.5 * L - 0.2, cab_h), (xc, cab_h)],
        W,
    )
    cargo_len = L - cab_len - 0.15
    cargo = box((cargo_len, W, H - floor), (-0.5 * L + 0.5 * cargo_len, 0.0, 0.5 * (H + floor)))
    chassis = box((L - cab_len, 1.0, floor - 0.5), (-0.5 * cab_len, 0.0, 0.5 * (floor + 0.5)))
    axles = [0.5 * L - 1.2, -0.5 * L + 1.5] + ([-0.5 * L + 2.8] if L > 8.0 else [])
    parts = [cab, cargo, chassis, *_wheels(axles, W, r, 0.3)]
    return _finish("truck", {"body": Mesh.merge(parts)}, {"length": L, "width": W, "height": H})


def bus(rng: np.random.Generator) -> StreetObject:
    """City bus: a long box with bevelled front and rear roof edges, two axles.
    10.5-13 x 2.5-2.55 x 3.0-3.3 m."""
    L, W, H = rng.uniform(10.5, 13.0), rng.uniform(2.5, 2.55), rng.uniform(3.0, 3.3)
    r = rng.uniform(0.48, 0.52)
    outline = [
        (-0.5 * L, 0.3),
        (0.5 * L, 0.3),
        (0.5 * L, H - 0.25),
        (0.5 * L - 0.2, H),
        (-0.5 * L + 0.1, H),
        (-0.5 * L, H - 0.1),
    ]
    parts = [_side_profile(outline, W), *_wheels([0.5 * L - 2.6, -0.5 * L + 3.0], W, r, 0.3)]
    return _finish("bus", {"body": Mesh.merge(parts)}, {"length": L, "width": W, "height": H})


def tram(rng: np.random.Generator) -> StreetObject:
    """Articulated tram: 3-5 box sections (sloped noses at both ends) joined by narrower
    bellows, one bogie under each section. 20-30 x 2.4-2.65 x 3.3-3.6 m."""
    L, W, H = rng.uniform(20.0, 30.0), rng.uniform(2.4, 2.65), rng.uniform(3.3, 3.6)
    n = int(rng.integers(3, 6))
    gap, floor = 0.35, 0.35
    sec = (L - (n - 1) * gap) / n
    parts = []
    for k in range(n):  # a handful of sections
        x0 = -0.5 * L + k * (sec + gap)
        x1 = x0 + sec
        back = 0.25 if k == 0 else 0.0
        front = 0.25 if k == n - 1 else 0.0
        outline = [
            (x0, floor),
            (x1, floor),
            (x1, H - 0.8),
            (x1 - front, H),
            (x0 + back, H),
            (x0, H - 0.8),
        ]
        parts.append(_side_profile(outline, W))
        parts.append(box((1.8, W - 0.5, 0.55), (0.5 * (x0 + x1), 0.0, 0.275)))
        if k < n - 1:
            parts.append(box((gap + 0.1, W - 0.3, H - 0.9), (x1 + 0.5 * gap, 0.0, 0.5 * H + 0.1)))
    params = {"length": L, "width": W, "height": H, "sections": float(n)}
    return _finish("tram", {"body": Mesh.merge(parts)}, params)


def trailer(rng: np.random.Generator) -> StreetObject:
    """Box trailer on one axle with a drawbar (SemanticKITTI other-vehicle; an image model
    trained on Cityscapes has no class for it). 2.5-4.5 x 1.5-2.1 x 1.2-2.3 m."""
    L, W = rng.uniform(2.5, 4.5), rng.uniform(1.5, 2.1)
    H = rng.uniform(1.2, 2.3)
    r, floor = rng.uniform(0.25, 0.32), rng.uniform(0.5, 0.65)
    bar = rng.uniform(1.0, 1.4)
    body = box((L, W, H - floor), (-0.5 * bar, 0.0, 0.5 * (H + floor)))
    drawbar = box((bar, 0.12, 0.1), (0.5 * L, 0.0, floor - 0.05))
    parts = [body, drawbar, *_wheels([-0.5 * bar], W, r, 0.18)]
    return _finish("trailer", {"body": Mesh.merge(parts)}, {"length": L, "width": W, "height": H})


def caravan(rng: np.random.Generator) -> StreetObject:
    """Touring caravan: a tall box with a rounded front (bevelled roof edges), one or two axles
    under its middle, a drawbar with a jockey wheel (SemanticKITTI other-vehicle; Cityscapes has
    no trained class for it). 5-7.5 x 2.2-2.5 x 2.4-2.7 m with the drawbar."""
    body_len, W, H = rng.uniform(4.0, 6.3), rng.uniform(2.2, 2.5), rng.uniform(2.4, 2.7)
    r, floor = rng.uniform(0.28, 0.33), rng.uniform(0.45, 0.55)
    bar = rng.uniform(1.0, 1.2)
    x0, x1 = -0.5 * body_len - 0.5 * bar, 0.5 * body_len - 0.5 * bar
    outline = [(x0, floor), (x1, floor), (x1, H - 0.5), (x1 - 0.25, H), (x0 + 0.1, H),
               (x0, H - 0.15)]  # fmt: skip
    drawbar = box((bar, 0.1, 0.1), (x1 + 0.5 * bar, 0.0, floor - 0.05))
    jockey = cylinder((x1 + 0.6 * bar, 0.0, 0.0), (x1 + 0.6 * bar, 0.0, floor - 0.1), 0.05, 6)
    middle = 0.5 * (x0 + x1)
    axles = [middle] if body_len < 5.5 else [middle - 0.45, middle + 0.45]
    parts = [_side_profile(outline, W), drawbar, jockey, *_wheels(axles, W, r, 0.18)]
    params = {"length": body_len + bar, "width": W, "height": H}
    return _finish("caravan", {"body": Mesh.merge(parts)}, params)


def excavator(rng: np.random.Generator) -> StreetObject:
    """Tracked excavator at rest: two crawler tracks, the turning upper body, the cab on its
    left, the boom and stick folded forward down to the bucket on the ground."""
    track_len, gauge = rng.uniform(3.0, 3.8), rng.uniform(2.2, 2.5)
    body_h, cab_h = rng.uniform(0.9, 1.1), rng.uniform(1.4, 1.7)
    tracks = [box((track_len, 0.55, 0.75), (0.0, sgn * 0.5 * gauge, 0.375)) for sgn in (-1, 1)]
    upper = box((2.8, gauge, body_h), (-0.3, 0.0, 0.8 + 0.5 * body_h))
    cab_z = 0.8 + body_h
    cab = box((1.0, 0.95, cab_h), (0.4, 0.5 * gauge - 0.5, cab_z + 0.5 * cab_h))
    boom_top = np.array([1.6, -0.3, cab_z + rng.uniform(1.6, 2.2)])
    boom = tube(np.stack([[0.8, -0.3, cab_z - 0.2], boom_top]), 0.22, 8)
    bucket_at = np.array([boom_top[0] + rng.uniform(1.2, 1.8), -0.3, 0.45])
    stick = tube(np.stack([boom_top, bucket_at]), 0.16, 8)
    bucket = box((0.8, 1.0, 0.7), bucket_at + [0.2, 0.0, -0.05])
    parts = [*tracks, upper, cab, boom, stick, bucket]
    params = {"track_length": track_len, "gauge": gauge}
    return _finish("excavator", {"body": Mesh.merge(parts)}, params)


def road_roller(rng: np.random.Generator) -> StreetObject:
    """Tandem road roller: a steel drum at each end (cylinders across y), the engine body
    between them and an open cab with a roof on four posts. 3.5-4.5 x 1.5-2.1 m."""
    L, W = rng.uniform(3.5, 4.5), rng.uniform(1.5, 2.1)
    r = rng.uniform(0.55, 0.7)
    drums = [
        cylinder((x, -0.5 * W, r), (x, 0.5 * W, r), r, 20) for x in (0.5 * L - r, -0.5 * L + r)
    ]
    body = box((L - 2.2 * r, W * 0.9, 1.0), (0.0, 0.0, r + 0.3))
    roof_z = r + rng.uniform(2.0, 2.3)
    posts = [
        cylinder((x, y, r + 0.8), (x, y, roof_z), 0.04, 6)
        for x in (-0.5, 0.5)
        for y in (-0.4 * W, 0.4 * W)
    ]
    roof = box((1.4, W * 0.95, 0.08), (0.0, 0.0, roof_z))
    parts = [*drums, body, *posts, roof]
    return _finish("roller", {"body": Mesh.merge(parts)}, {"length": L, "width": W})


# ----------------------------------------------------------------------------- market


def market_stall(rng: np.random.Generator) -> StreetObject:
    """A market stall: a table of goods (counter box) and a sloping awning on four posts that
    reaches out over the sidewalk in front of it (local -y: the side the customers stand).
    2-4 m wide, the awning 2-3 m deep at 2.1-2.6 m."""
    width, depth = rng.uniform(2.0, 4.0), rng.uniform(0.8, 1.2)
    reach = rng.uniform(2.0, 3.0)  # awning depth, from the back of the stall
    high, low = rng.uniform(2.4, 2.8), rng.uniform(2.1, 2.3)
    counter = box((width, depth, 0.9), (0.0, 0.0, 0.45))
    goods = box((width - 0.2, depth - 0.2, 0.25), (0.0, 0.0, 1.02))
    back_y, front_y = 0.5 * depth, 0.5 * depth - reach
    posts = [
        cylinder((x, y, 0.0), (x, y, z), 0.03, 6)
        for x in (-0.5 * width, 0.5 * width)
        for y, z in ((back_y, high), (front_y, low))
    ]
    awning = _side_profile(
        [(front_y, low), (back_y, high), (back_y, high + 0.04), (front_y, low + 0.04)], width
    )  # built in (y, z): turn it so its slope runs across the stall
    awning.vertices = awning.vertices[:, [1, 0, 2]]
    params = {"width": width, "depth": depth, "reach": reach}
    return _finish("stall", {"body": Mesh.merge([counter, goods, *posts, awning])}, params)


def crates(rng: np.random.Generator) -> StreetObject:
    """A stack of produce crates: 2-6 boxes of 0.5 x 0.35 x 0.3 m in up to three layers."""
    pieces = []
    count = int(rng.integers(2, 7))
    for k in range(count):
        column, layer = divmod(k, 3)
        pieces.append(box((0.5, 0.35, 0.3), (0.55 * column, 0.0, 0.15 + 0.31 * layer)))
    return _finish("crates", {"body": Mesh.merge(pieces)}, {"count": float(count)})


def bike_rack(rng: np.random.Generator, hoops: int) -> StreetObject:
    """Sheffield stands: `hoops` inverted-U tubes 0.8 m high, 0.7 m long, 1 m apart along x;
    bicycles park along y beside them."""
    pieces = []
    for k in range(hoops):
        x = k * 1.0
        u = np.array([[x, -0.35, 0.0], [x, -0.35, 0.8], [x, 0.35, 0.8], [x, 0.35, 0.0]])
        pieces.append(tube(u, 0.025, 8))
    return _finish("bike-rack", {"body": Mesh.merge(pieces)}, {"hoops": float(hoops)})


def canopy(rng: np.random.Generator, length: float) -> StreetObject:
    """A shop's canopy fixed to its facade: a slab `length` long reaching 1.5-2.5 m out over the
    sidewalk (local -y) at 2.6-3.0 m, hung from the wall (no posts)."""
    reach, z = rng.uniform(1.5, 2.5), rng.uniform(2.6, 3.0)
    slab = box((length, reach, 0.12), (0.0, -0.5 * reach, z))
    # not stood on the ground (`_finish`): it hangs at its height
    return StreetObject("canopy", {"body": slab}, (length, reach, z), {"reach": reach})


# ----------------------------------------------------------------------------- people


def _person(
    rng: np.random.Generator, H: float, hip: np.ndarray, seated: bool
) -> tuple[Mesh, float]:
    """Torso, head and arms of a person of height `H` whose hips sit at `hip`; legs are the
    caller's (standing or pedalling). Returns the mesh and the shoulder half-width."""
    w = rng.uniform(0.32, 0.4)
    depth = rng.uniform(0.2, 0.27)
    lean = 0.35 if seated else 0.0  # forward lean of the torso (rad)
    torso_len = 0.3 * H
    shoulder = hip + torso_len * np.array([np.sin(lean), 0.0, np.cos(lean)])
    centre = 0.5 * (hip + shoulder)
    torso = ellipsoid(centre, (0.5 * depth, 0.5 * w, 0.5 * torso_len + 0.04), 2)
    if seated:
        V = torso.vertices - centre
        c, s = np.cos(lean), np.sin(lean)
        torso.vertices = V @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + centre
    head_r = 0.0657 * H  # neck 0.0886 H: a standing person's head top is at H
    head_c = shoulder + np.array([0.03, 0.0, 0.0886 * H + head_r])
    head = ellipsoid(head_c, (0.85 * head_r, 0.72 * head_r, head_r), 2)
    neck = cylinder(shoulder - [0, 0, 0.05], head_c - [0, 0, 0.5 * head_r], 0.05, 10)
    return Mesh.merge([torso, head, neck]), 0.5 * w


def pedestrian(rng: np.random.Generator) -> StreetObject:
    """Walking person, 1.55-1.95 m tall, ~0.5 m wide: two legs (in stride), ellipsoid torso,
    head, hanging arms."""
    H = rng.uniform(1.55, 1.95)
    hip = np.array([0.0, 0.0, 0.48 * H])
    stride = rng.uniform(0.0, 0.35)
    body, half_w = _person(rng, H, hip, seated=False)
    legs = [  # a short upright foot segment keeps the sole flat on the ground
        tube(
            [
                (sgn * 0.5 * stride, sgn * 0.09, 0.0),
                (sgn * 0.5 * stride, sgn * 0.09, 0.05),
                (0.0, sgn * 0.09, hip[2] + 0.05),
            ],
            0.07,
            12,
        )
        for sgn in (-1.0, 1.0)
    ]
    shoulder_z = hip[2] + 0.3 * H - 0.03
    arms = [
        cylinder(
            (0.0, sgn * (half_w + 0.03), shoulder_z),
            (-sgn * 0.4 * stride, sgn * (half_w + 0.04), hip[2] - 0.05),
            0.04,
            10,
        )
        for sgn in (-1.0, 1.0)
    ]
    mesh = Mesh.merge([body, *legs, *arms])
    return _finish("pedestrian", {"body": mesh}, {"height": H, "stride": stride})


def cyclist(rng: np.random.Generator) -> StreetObject:
    """Bicycle (thin-disc wheels and frame tubes, ~1.75 m long) and its rider, as the separate
    meshes "bicycle" and "rider" so they can be labelled BICYCLE / BICYCLIST."""
    r = rng.uniform(0.33, 0.36)
    wb = rng.uniform(1.0, 1.1)
    rear, front = np.array([-0.5 * wb, 0.0, r]), np.array([0.5 * wb, 0.0, r])
    bb = np.array([-0.5 * wb + 0.42, 0.0, 0.28])
    saddle = np.array([-0.5 * wb + 0.3, 0.0, rng.uniform(0.85, 0.95)])
    head_top = np.array([0.5 * wb - 0.12, 0.0, saddle[2] - 0.05])
    head_bot = head_top + np.array([0.05, 0.0, -0.16])
    bar = head_top + np.array([-0.05, 0.0, 0.12])
    frame = [
        (rear, bb),
        (rear, saddle - [0, 0, 0.05]),
        (bb, saddle),
        (bb, head_bot),
        (saddle - [0, 0, 0.08], head_top),
        (head_bot, front),
        (head_top, bar),
    ]
    bike = [cylinder((x, -0.025, r), (x, 0.025, r), r, 24) for x in (rear[0], front[0])]
    bike += [cylinder(a, b, 0.02, 8) for a, b in frame]
    bike.append(cylinder(bar + [0, -0.28, 0], bar + [0, 0.28, 0], 0.015, 8))
    bike.append(box((0.25, 0.12, 0.05), saddle + [0.0, 0.0, 0.025]))

    H = rng.uniform(1.6, 1.9)
    hip = saddle + np.array([0.0, 0.0, 0.1])
    body, half_w = _person(rng, H, hip, seated=True)
    crank = rng.uniform(0.0, 2.0 * np.pi)
    legs = []
    for sgn, phase in ((-1.0, 0.0), (1.0, np.pi)):  # two legs: hip, knee, pedal
        pedal = bb + np.array(
            [0.17 * np.cos(crank + phase), sgn * 0.15, 0.17 * np.sin(crank + phase)]
        )
        hp = hip + [0.0, sgn * 0.1, -0.05]
        knee = 0.5 * (hp + pedal) + np.array([0.18, 0.0, 0.1])
        legs.append(tube(np.stack([hp, knee, pedal]), 0.06, 10))
    shoulder = hip + 0.3 * H * np.array([np.sin(0.35), 0.0, np.cos(0.35)])
    arms = [
        tube(
            np.stack([shoulder + [0, sgn * (half_w + 0.02), -0.03], bar + [0, sgn * 0.24, 0]]),
            0.04,
            10,
        )
        for sgn in (-1.0, 1.0)
    ]
    meshes = {"bicycle": Mesh.merge(bike), "rider": Mesh.merge([body, *legs, *arms])}
    return _finish("cyclist", meshes, {"wheel_radius": r, "wheelbase": wb, "rider_height": H})


# ----------------------------------------------------------------------------- roadside


def tree(rng: np.random.Generator) -> StreetObject:
    """Street tree: trunk (cylinder, radius 0.1-0.25, height 2-3.5) and crown (ellipsoid,
    horizontal radius 1.5-3) above it, overlapping the trunk top slightly."""
    r_t, h_t = rng.uniform(0.1, 0.25), rng.uniform(2.0, 3.5)
    R = rng.uniform(1.5, 3.0)
    Rv = R * rng.uniform(0.8, 1.3)
    trunk = cylinder((0.0, 0.0, 0.0), (0.0, 0.0, h_t), r_t, 12)
    crown = ellipsoid((0.0, 0.0, h_t + 0.85 * Rv), (R, R * rng.uniform(0.9, 1.1), Rv), 2)
    params = {"trunk_radius": r_t, "trunk_height": h_t, "crown_radius": R, "crown_height": Rv}
    return _finish("tree", {"trunk": trunk, "crown": crown}, params)


def bush(rng: np.random.Generator) -> StreetObject:
    """A free-grown bush: a round mass of leaves 0.8-2.5 m across, 0.6-1.8 m tall
    (`meshes.foliage`), standing on the ground."""
    width, height = rng.uniform(0.8, 2.5), rng.uniform(0.6, 1.8)
    radii = (0.5 * width * rng.uniform(0.8, 1.4), 0.5 * width, 0.5 * height)
    leaves = foliage(radii, rng, roundness=2.0)
    return _finish("bush", {"foliage": leaves}, {"width": width, "height": height})


def hedge(rng: np.random.Generator, length: float) -> StreetObject:
    """A trimmed hedge `length` long (local x), 0.5-1.2 m deep, 0.8-2.0 m tall: leaves in a
    boxy volume (`meshes.foliage`, roundness 4)."""
    depth, height = rng.uniform(0.5, 1.2), rng.uniform(0.8, 2.0)
    leaves = foliage((0.5 * length, 0.5 * depth, 0.5 * height), rng, roundness=4.0)
    return _finish("hedge", {"foliage": leaves}, {"depth": depth, "height": height})


def pole(rng: np.random.Generator, arm: bool | None = None) -> StreetObject:
    """Street lamp or utility pole: height 5-9 m, radius 0.08-0.15; with `arm` (drawn when
    None) a bent arm reaching 1-2.5 m out along -y (the road) carrying a lamp head."""
    H, r = rng.uniform(5.0, 9.0), rng.uniform(0.08, 0.15)
    has_arm = bool(rng.random() < 0.6) if arm is None else bool(arm)
    parts = [cylinder((0.0, 0.0, 0.0), (0.0, 0.0, H), r, 16)]
    params = {"height": H, "radius": r, "arm": 0.0}
    if has_arm:
        reach = rng.uniform(1.0, 2.5)
        a = np.linspace(0.0, 0.5 * np.pi, 10)
        bend = 0.4
        arm_pts = np.column_stack(
            [np.zeros_like(a), -bend * (1.0 - np.cos(a)), H - 0.6 + bend * np.sin(a)]
        )
        arm_pts = np.vstack([arm_pts, [0.0, -reach, H - 0.6 + bend]])
        parts.append(tube(arm_pts, 0.05, 10))
        parts.append(box((0.25, 0.5, 0.12), (0.0, -reach + 0.15, H - 0.6 + bend - 0.1)))
        params["arm"] = reach
    return _finish("lamp" if has_arm else "pole", {"pole": Mesh.merge(parts)}, params)


SIGN_SHAPES = ("square", "round", "triangle")


def sign(rng: np.random.Generator, shape: str | None = None) -> StreetObject:
    """Traffic sign: pole (2.2-3 m, radius 0.03-0.05) and a 2 cm thick plate (0.6-0.9 m,
    square, round or triangle) at its top, in front of the pole on the -y side, its face
    (normal) pointing along local -y."""
    H, r = rng.uniform(2.2, 3.0), rng.uniform(0.03, 0.05)
    s = rng.uniform(0.6, 0.9)
    shape = str(shape if shape is not None else SIGN_SHAPES[int(rng.integers(3))])
    t = 0.02
    yc, zc = -(r + 0.01 + 0.5 * t), H - 0.5 * s
    if shape == "square":
        plate = box((s, t, s), (0.0, yc, zc))
    elif shape == "round":
        plate = cylinder((0.0, yc + 0.5 * t, zc), (0.0, yc - 0.5 * t, zc), 0.5 * s, 32)
    elif shape == "triangle":
        h = 0.5 * np.sqrt(3.0) * s
        tri = [(-0.5 * s, H - h), (0.5 * s, H - h), (0.0, H)]
        plate = _side_profile(tri, t, y0=yc)
    else:
        raise ValueError(f"unknown sign shape {shape!r}; use one of {SIGN_SHAPES}")
    post = cylinder((0.0, 0.0, 0.0), (0.0, 0.0, H), r, 12)
    params = {"height": H, "radius": r, "plate": s}
    return _finish(f"sign-{shape}", {"pole": post, "plate": plate}, params)


# ----------------------------------------------------------------------------- barriers


def median_barrier(line: np.ndarray, rng: np.random.Generator) -> Mesh:
    """A concrete safety-shape (New Jersey) barrier along `line` (K, 3, on the ground), WORLD
    coordinates: 0.61 m base, a 75 mm vertical reveal, the 55 degree lower face up to 0.33 m,
    the 84 degree upper face to a 0.15 m wide top, 0.81 m high (one in three 1.07 m, the tall
    variant). A guardrail to the eye of a rotating scanner, but no posts and no beam: the
    guardrail classifier must call it other."""
    tall = rng.random() < 1.0 / 3.0
    top = 1.07 if tall else 0.81
    half = np.array([0.305, 0.305, 0.125, 0.075])
    height = np.array([0.0, 0.075, 0.33, top])
    profile = np.column_stack([np.r_[half, -half[::-1]], np.r_[height, height[::-1]]])
    return sweep_profile(profile, np.asarray(line, dtype=np.float64))


# ----------------------------------------------------------------------------- buildings


def _stations(line: np.ndarray) -> np.ndarray:
    return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]


def _at(line: np.ndarray, S: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, S, line[:, k]) for k in range(3)])


def _footprint(w: float, D: float, notches: list[tuple[float, float, float]]) -> np.ndarray:
    """Counter-clockwise block outline: facade on y = 0 from x = 0 to w, building towards -y
    down to -D, with rectangular notches (x0, x1, depth) cut into the facade."""
    pts = [(0.0, -D), (w, -D), (w, 0.0)]
    for x0, x1, dep in sorted(notches, reverse=True):
        pts += [(x1, 0.0), (x1, -dep), (x0, -dep), (x0, 0.0)]
    pts.append((0.0, 0.0))
    return np.array(pts)


def facade(
    baseline: np.ndarray, height: float, rng: np.random.Generator, depth: float = 8.0
) -> Mesh:
    """A row of building blocks (WORLD coordinates) whose facades stand on `baseline` (K, 3),
    the building line: the road is on the LEFT of the baseline's direction, the buildings on
    its right, `depth` deep. Blocks are 8-20 m wide (the last one fills what is left, >= 3 m),
    0.7-1.3 x `height` tall, with no gap (half of them) or a 0.3-1.5 m gap between them, and
    0-2 entrance recesses each 1.5-4 m wide, 0.5-1.5 m deep: ground-floor doorways 2.2-3.5 m
    high, or (one in four) full-height recesses. Blocks start 0.2 m below the ground line."""
    line = np.asarray(baseline, dtype=np.float64).reshape(-1, 3)
    S = _stations(line)
    total = S[-1]
    meshes: list[Mesh] = []
    s = 0.0
    while total - s >= 3.0:  # one iteration per block
        w = min(rng.uniform(8.0, 20.0), total - s)
        p0, p1 = _at(line, S, s), _at(line, S, s + w)
        ex = p1 - p0
        ex[2] = 0.0
        wc = float(np.linalg.norm(ex))
        ex /= wc
        ey = np.array([-ex[1], ex[0], 0.0])  # left: towards the road
        z0 = min(p0[2], p1[2]) - 0.2
        h = height * rng.uniform(0.7, 1.3)
        door_h = min(rng.uniform(2.2, 3.5), 0.6 * h)
        ground_cut, full_cut = [], []
        n_rec = int(rng.integers(0, 3))
        slot = wc / max(n_rec, 1)
        for k in range(n_rec):
            rw = min(rng.uniform(1.5, 4.0), slot - 1.0)
            if rw < 1.5:
                continue
            x0 = k * slot + rng.uniform(0.5, slot - rw - 0.5)
            cut = (x0, x0 + rw, rng.uniform(0.5, 1.5))
            (full_cut if rng.random() < 0.25 else ground_cut).append(cut)
        levels = [(z0, z0 + 0.2 + h, full_cut)]
        if ground_cut:
            levels = [
                (z0, z0 + 0.2 + door_h, full_cut + ground_cut),
                (z0 + 0.2 + door_h, z0 + 0.2 + h, full_cut),
            ]
        for za, zb, cuts in levels:
            m = extrude_polygon(_footprint(wc, depth, cuts), za, zb)
            V = m.vertices
            m.vertices = np.column_stack(
                [
                    p0[0] + V[:, 0] * ex[0] + V[:, 1] * ey[0],
                    p0[1] + V[:, 0] * ex[1] + V[:, 1] * ey[1],
                    V[:, 2],
                ]
            )
            meshes.append(m)
        s += w + (0.0 if rng.random() < 0.5 else rng.uniform(0.3, 1.5))
    return Mesh.merge(meshes)
