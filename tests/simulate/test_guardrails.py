"""Guardrails: poles on the line at the spacing, identical units, mesh on the model, W-beam."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.core.labels import Part
from app.simulate.guardrail_distance import surface_distance
from app.simulate.guardrails import (
    PIPE_DESIGNS,
    W_BEAM_CORRUGATION,
    W_BEAM_DEPTH,
    beam_guardrail,
    pipe_guardrail,
    pole_stations,
    w_beam_section,
)

R = 40.0


def curve(length: float = 41.0, step: float = 0.1, z: float = 0.25) -> np.ndarray:
    """Counter-clockwise arc of radius R about the origin, sampled every `step` m."""
    a = np.linspace(0.0, length / R, int(round(length / step)) + 1)
    return np.column_stack([R * np.cos(a), R * np.sin(a), np.full_like(a, z)])


def straight(length: float = 21.0) -> np.ndarray:
    t = np.linspace(0.0, length, 8)
    heading = np.radians(30.0)
    return np.column_stack([10 + t * np.cos(heading), -4 + t * np.sin(heading), np.full(8, 1.5)])


def part_vertices(g, part: Part) -> np.ndarray:
    m = g.mesh
    return m.vertices[np.unique(m.triangles[m.part == part])]


def to_unit_frame(points: np.ndarray, base: np.ndarray, nxt: np.ndarray) -> np.ndarray:
    ex = (nxt - base) / np.linalg.norm(nxt - base)
    ey = np.cross([0.0, 0.0, 1.0], ex)
    ey /= np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    return (points - base) @ np.stack([ex, ey, ez]).T


def only_floats(x) -> bool:
    if isinstance(x, dict):
        return all(isinstance(k, str) and only_floats(v) for k, v in x.items())
    if isinstance(x, list):
        return all(only_floats(v) for v in x)
    return x is None or type(x) in (float, int, str, bool)


def test_pole_stations_on_a_curve_are_equally_spaced() -> None:
    line = curve(41.0)
    pts, st = pole_stations(line, 2.0)
    assert len(pts) == 21  # 20 whole units in 41 m, the last partial unit dropped
    np.testing.assert_allclose(np.linalg.norm(np.diff(pts, axis=0), axis=1), 2.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pts[:, :2], axis=1), R, atol=2e-4)  # on the line
    arc = R * np.diff(np.unwrap(np.arctan2(pts[:, 1], pts[:, 0])))
    np.testing.assert_allclose(arc, 2.0, atol=1e-3)  # arc-length spacing too
    np.testing.assert_allclose(np.diff(st), 2.0, atol=1e-3)


@pytest.mark.parametrize("design", PIPE_DESIGNS)
def test_pipe_guardrail_poles_spacing_on_curve(design: str) -> None:
    g = pipe_guardrail(curve(41.0), np.random.default_rng(0), pole_spacing=2.0, design=design)
    m = g.model
    bases = np.array([p["base"] for p in m["poles"]])
    tops = np.array([p["top"] for p in m["poles"]])
    assert m["unit_count"] == len(bases) - 1 == 20 and m["unit_length"] == 2.0
    np.testing.assert_allclose(np.linalg.norm(np.diff(bases, axis=0), axis=1), 2.0)
    arc = R * np.diff(np.arctan2(bases[:, 1], bases[:, 0]))
    np.testing.assert_allclose(arc, 2.0, atol=1e-3)
    h = tops[:, 2] - bases[:, 2]
    assert np.allclose(h, h[0]) and 0.8 <= h[0] <= 1.1
    np.testing.assert_allclose(tops[:, :2], bases[:, :2])  # vertical
    radii = [p["radius"] for p in m["poles"]]
    assert min(radii) >= 0.03 and max(radii) <= 0.04
    pipes = m["pipes"]
    roles = {p["role"] for p in pipes}
    assert "top_rail" in roles
    assert {"simple": "vertical", "diagonal": "diagonal", "curved": "curved"}[design] in roles
    for p in pipes:
        lo = 0.024 if p["role"] == "top_rail" else 0.012
        hi = 0.03 if p["role"] == "top_rail" else 0.025
        assert lo <= p["radius"] <= hi
    top = [p for p in pipes if p["role"] == "top_rail"]
    ends = np.array([p["polyline"][0] for p in top])
    np.testing.assert_allclose(ends, tops[:-1])  # the top rail runs along the pole tops


@pytest.mark.parametrize("design", PIPE_DESIGNS)
@pytest.mark.parametrize("line", [straight(), curve(20.0, z=0.0)], ids=["straight", "curve"])
def test_pipe_guardrail_units_are_identical(design: str, line: np.ndarray) -> None:
    g = pipe_guardrail(line, np.random.default_rng(11), design=design)
    m = g.model
    bases = np.array([p["base"] for p in m["poles"]])
    units: dict[int, list] = {}
    for p in m["pipes"]:
        units.setdefault(p["unit"], []).append(p)
    assert sorted(units) == list(range(m["unit_count"]))
    ref = [
        (to_unit_frame(np.array(p["polyline"]), bases[0], bases[1]), p["radius"], p["role"])
        for p in units[0]
    ]
    for i, pipes in units.items():
        assert len(pipes) == len(ref)
        for p, (poly0, r0, role0) in zip(pipes, ref, strict=True):
            poly = to_unit_frame(np.array(p["polyline"]), bases[i], bases[i + 1])
            np.testing.assert_allclose(poly, poly0, atol=1e-9)
            assert (p["radius"], p["role"]) == (r0, role0)
    local = to_unit_frame(
        np.array([q for p in units[0] for q in p["polyline"]]), bases[0], bases[1]
    )
    np.testing.assert_allclose(local[:, 1], 0.0, atol=1e-9)  # pipes in the unit plane
    assert local[:, 0].min() >= -1e-9 and local[:, 0].max() <= 2.0 + 1e-9


@pytest.mark.parametrize("design", PIPE_DESIGNS)
def test_pipe_mesh_lies_on_the_model_and_parts_are_labelled(design: str) -> None:
    g = pipe_guardrail(curve(30.0), np.random.default_rng(5), design=design)
    assert set(np.unique(g.mesh.part)) == {Part.PIPE, Part.POLE}
    for part in (Part.PIPE, Part.POLE):
        d = surface_distance(g.model, part_vertices(g, part))
        assert d.max() < 1e-3
    text = json.dumps(g.model)
    assert only_floats(json.loads(text)) and only_floats(g.model)
    assert g.model["beam"] is None and g.model["kind"] == "pipe"
    assert all(type(c) is float for p in g.model["pipes"] for q in p["polyline"] for c in q)


def test_points_5cm_off_a_pipe_are_5cm_away() -> None:
    g = pipe_guardrail(straight(), np.random.default_rng(2), design="simple")
    rng = np.random.default_rng(0)
    pts = []
    for p in g.model["pipes"]:
        if p["role"] != "top_rail":
            continue
        a, b = np.array(p["polyline"][0]), np.array(p["polyline"][-1])
        d = (b - a) / np.linalg.norm(b - a)
        side = np.cross([0.0, 0.0, 1.0], d)
        side /= np.linalg.norm(side)
        up = np.cross(d, side)
        t = rng.uniform(0.25, 0.75, 50)
        phi = rng.uniform(0.0, np.pi, 50)  # upper half: nothing else is near there
        off = np.cos(phi)[:, None] * side + np.sin(phi)[:, None] * up
        pts.append(a + t[:, None] * (b - a) + (p["radius"] + 0.05) * off)
    d = surface_distance(g.model, np.concatenate(pts))
    np.testing.assert_allclose(d, 0.05, atol=1e-9)
    # a point straight above a pole top is (height above the rail axis - rail radius) away
    top = np.array(g.model["poles"][3]["top"])
    r_top = next(p["radius"] for p in g.model["pipes"] if p["role"] == "top_rail")
    above = surface_distance(g.model, (top + [0.0, 0.0, 0.3])[None])
    assert above[0] == pytest.approx(0.3 - r_top)


def test_surface_distance_far_points_and_inside_points() -> None:
    g = pipe_guardrail(straight(), np.random.default_rng(2), design="diagonal")
    pole = g.model["poles"][2]
    base, top, r = np.array(pole["base"]), np.array(pole["top"]), pole["radius"]
    axis_mid = base + 0.1 * (top - base)
    assert surface_distance(g.model, axis_mid[None])[0] == pytest.approx(r)  # inside a pole
    far = np.array([[0.0, 0.0, 50.0]])
    assert surface_distance(g.model, far)[0] > 1.0
    exact = surface_distance(g.model, far, cutoff=np.inf)[0]
    pts = np.concatenate(g.model["pipes"][0]["polyline"])
    assert exact == pytest.approx(
        np.linalg.norm(far - pts.reshape(-1, 3), axis=1).min() - 0.03, abs=0.1
    )


def test_w_beam_section_has_two_peaks() -> None:
    sec = w_beam_section()
    u, v = sec[:, 0], sec[:, 1]
    assert v.max() - v.min() == pytest.approx(W_BEAM_DEPTH)
    peaks = np.flatnonzero((u[1:-1] > u[:-2]) & (u[1:-1] > u[2:])) + 1
    assert len(peaks) == 2
    np.testing.assert_allclose(u[peaks], W_BEAM_CORRUGATION)
    np.testing.assert_allclose(np.sort(v[peaks]), [-W_BEAM_DEPTH / 4, W_BEAM_DEPTH / 4])
    valley = np.flatnonzero((u[1:-1] < u[:-2]) & (u[1:-1] < u[2:])) + 1
    assert len(valley) == 1 and abs(v[valley[0]]) < 1e-12


@pytest.mark.parametrize("shape", ["round", "box"])
@pytest.mark.parametrize("road_side", ["left", "right"])
def test_beam_guardrail_geometry_and_mesh_on_model(shape: str, road_side: str) -> None:
    line = curve(30.0)
    g = beam_guardrail(
        line,
        np.random.default_rng(4),
        post_spacing=4.0,
        road_side=road_side,
        post_shape=shape,
        blockout=True,
    )
    m = g.model
    assert m["kind"] == "beam" and m["post_shape"] == shape and m["unit_length"] == 4.0
    bases = np.array([p["base"] for p in m["poles"]])
    assert len(bases) == m["unit_count"] + 1 == 8
    np.testing.assert_allclose(np.linalg.norm(np.diff(bases, axis=0), axis=1), 4.0)
    h = np.array([p["top"][2] - p["base"][2] for p in m["poles"]])
    assert np.all((h >= 0.75) & (h <= 0.8))
    if shape == "round":
        assert all(0.05 <= p["radius"] <= 0.07 for p in m["poles"])
    path = np.array(m["beam"]["path"])
    centre = m["beam"]["centre_height"]
    assert centre >= 0.55 and centre + W_BEAM_DEPTH / 2 <= h.min() + 1e-9
    np.testing.assert_allclose(path[:, 2] - 0.25, centre)
    # the beam is offset towards the road: the line turns left (ccw), so left = inside
    rad = np.linalg.norm(path[:, :2], axis=1)
    off = R - rad if road_side == "left" else rad - R
    assert np.all((off >= 0.1 - 1e-3) & (off <= 0.2 + 2e-3))
    sec = np.array(m["beam"]["section"])
    assert (np.sign(sec[:, 0]) >= 0).all() if road_side == "left" else (sec[:, 0] <= 0).all()
    assert set(np.unique(g.mesh.part)) == {Part.BEAM, Part.POLE}
    for part in (Part.BEAM, Part.POLE):
        assert surface_distance(m, part_vertices(g, part)).max() < 1e-3
    assert only_floats(json.loads(json.dumps(m))) and only_floats(m)
    assert len(m["spacers"]) == len(bases)


def test_beam_points_off_the_sheet() -> None:
    line = np.column_stack([np.linspace(0, 20, 5), np.zeros(5), np.zeros(5)])
    g = beam_guardrail(line, np.random.default_rng(1), post_shape="round", blockout=False)
    path = np.array(g.model["beam"]["path"])
    # from the road side (+y), 0.2 m in front of the crest of the upper peak
    peak_y = path[0, 1] + W_BEAM_CORRUGATION
    x = np.linspace(1.0, 19.0, 7)  # between posts is irrelevant: posts are behind the beam
    p = np.column_stack([x, np.full(7, peak_y + 0.2), np.full(7, path[0, 2] + W_BEAM_DEPTH / 4)])
    np.testing.assert_allclose(surface_distance(g.model, p), 0.2, atol=1e-9)


def test_guardrails_are_deterministic_and_reject_short_lines() -> None:
    line = curve(12.0)
    a = pipe_guardrail(line, np.random.default_rng(9))
    b = pipe_guardrail(line, np.random.default_rng(9))
    assert a.model == b.model
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    with pytest.raises(ValueError):
        pipe_guardrail(curve(1.5), np.random.default_rng(0))
    with pytest.raises(ValueError):
        beam_guardrail(curve(3.0), np.random.default_rng(0), post_spacing=4.0)
