"""The whole guardrail from its points (Matsumoto, Mori & Masuda, sections 4.1-4.4).

`reconstruct_guardrail` runs the reconstruction half of the guardrail pipeline as the paper's
stages: rail course -> poles -> unit shapes -> superimposition -> pipes or beam -> assembly,
where "3D models of the unit shape are copied between poles". Every copy is placed between its
own two poles along the real rail path: a unit that was stacked goes back through its own frame
and registration (so it follows the data), any other pair of poles (inferred in a scan gap, or
a unit with too few points) gets the unit frame built from the two poles, with x stretched to
their distance. Beams are swept along the path through the poles. Poles are cylinders from the
ground to their top.

Kind "auto" takes the paper's cue: a beam fills a relatively large rectangle with points, so the
stacked unit is a beam when its narrow vertical slices show a continuous band of points taller
than `band.min_band` (0.2 m; a W-beam is 0.31 m, a pipe at most ~6 cm) in most slices
(`beams.looks_like_beam`), else pipes.

Each stage's settings are one group of `config.ReconstructionConfig` (`poles`, `units`,
`superimpose`, `pipes`, `beams`, `band`, ...), which the stage's function takes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.pipelines.guardrail import meshes
from app.pipelines.guardrail.beams import BeamModel, beam_section, looks_like_beam
from app.pipelines.guardrail.config import ReconstructionConfig
from app.pipelines.guardrail.pipes import PipeModel, reconstruct_pipes
from app.pipelines.guardrail.poles import Pole, detect_poles, place_poles, pole_spacing
from app.pipelines.guardrail.rail_curve import RailCurve, rail_curve
from app.pipelines.guardrail.superimpose import Stack, superimpose
from app.pipelines.guardrail.units import Unit, split_units, unit_frame

# pole radius when no pole's own arc fixes it, once the kind is known (not from the paper:
# Japanese pipe guardrail posts are 60-76 mm pipes, W-beam posts ~114-140 mm pipes or H posts)
POLE_RADIUS_PRIOR = {"pipe": 0.035, "beam": 0.065}


@dataclass
class ReconstructedGuardrail:
    """One reconstructed guardrail: poles, the stacked unit's model, the assembled mesh
    (world coordinates) and a JSON-ready `model`."""

    kind: str  # "pipe", "beam", or "unknown" (fewer than two poles)
    poles: list[Pole]
    units_stacked: int
    icp_residual: float  # m, median ICP inlier RMSE of the stacked units
    pipes: PipeModel | None
    beam: BeamModel | None
    vertices: np.ndarray  # (V, 3) float64 world
    faces: np.ndarray  # (F, 3) int64
    model: dict
    placements: list[np.ndarray] = field(default_factory=list)  # per pole pair: 4x4 affine
    stack: Stack | None = field(default=None, repr=False)
    curve: RailCurve | None = field(default=None, repr=False)

    def without_mesh(self) -> ReconstructedGuardrail:
        """The guardrail without its mesh and working data (stack, curve, placements), once its
        mesh is written: the model (`model`, poles, unit models) stays, for the store."""
        empty = np.zeros((0, 3))
        return replace(self, vertices=empty, faces=np.zeros((0, 3), np.int64), placements=[],
                       stack=None, curve=None)  # fmt: skip


def _affine_apply(A: np.ndarray, q: np.ndarray) -> np.ndarray:
    return q @ A[:3, :3].T + A[:3, 3]


def _placements(
    poles: list[Pole], units: list[Unit], stack: Stack | None, ref: Unit | None
) -> list[np.ndarray]:
    """Per consecutive pole pair, the affine map from the reference unit frame (the model's)
    to world."""
    by_pair = {u.poles[0]: u for u in units}
    plane = [  # the units' plane offsets from their pole line
        float(
            (u.frame.origin - 0.5 * (poles[u.poles[0]].base_point + poles[u.poles[1]].base_point))
            @ u.frame.ez
        )
        for u in units
    ]
    offset = float(np.median(plane)) if plane else 0.0
    ref_len = ref.length if ref is not None else None
    out = []
    for j in range(len(poles) - 1):
        u = by_pair.get(j)
        if u is not None and stack is not None and u.index in stack.transforms:
            out.append(u.frame.matrix @ np.linalg.inv(stack.transforms[u.index]))
            continue
        h = ref.height if ref is not None else None  # the origin half way up, as for the ref
        frame, length, _ = unit_frame(poles[j], poles[j + 1], None, plane_offset=offset, height=h)
        S = np.diag([length / ref_len if ref_len else 1.0, 1.0, 1.0, 1.0])
        out.append(frame.matrix @ S)
    return out


def _pipe_mesh(
    model: PipeModel, placements: list[np.ndarray], segments: int
) -> tuple[meshes.Mesh, list[dict]]:
    parts, world = [], []
    for j, A in enumerate(placements):
        for p in model.pipes:
            W = _affine_apply(A, p.polyline)
            parts.append(meshes.tube(W, p.radius, segments))
            world.append({"polyline": W.tolist(), "radius": p.radius, "kind": p.kind, "unit": j})
    return meshes.merge(parts), world


def _beam_path(
    beam: BeamModel, placements: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Path vertices at the poles (adjacent copies averaged) with their across / up axes."""
    xl, xr = beam.x_range
    ends, across, up = [], [], []
    for A in placements:
        ends.append(_affine_apply(A, np.array([[xl, 0.0, 0.0], [xr, 0.0, 0.0]])))
        ez = A[:3, 2] / np.linalg.norm(A[:3, 2])
        ey = A[:3, 1] / np.linalg.norm(A[:3, 1])
        across.append(ez)
        up.append(ey)
    n = len(placements)
    path = np.empty((n + 1, 3))
    acr = np.empty((n + 1, 3))
    upv = np.empty((n + 1, 3))
    for k in range(n + 1):
        pts = [ends[i][1] for i in (k - 1,) if 0 <= i < n] + [ends[i][0] for i in (k,) if i < n]
        path[k] = np.mean(pts, axis=0)
        a = [across[i] for i in (k - 1, k) if 0 <= i < n]
        acr[k] = np.mean(a, axis=0) / np.linalg.norm(np.mean(a, axis=0))
        u = [up[i] for i in (k - 1, k) if 0 <= i < n]
        upv[k] = np.mean(u, axis=0) / np.linalg.norm(np.mean(u, axis=0))
    return path, acr, upv


def _posts_behind_beam(poles: list[Pole], points: np.ndarray, curve: RailCurve) -> None:
    """Without a trajectory a pole seen from one side does not know which side that was; a
    beam hangs on the road side of its posts, so the post's centre lies away from the beam
    (the bulk of the points around it)."""
    s, d = curve.project(points[:, :2])
    for p in poles:
        if p.away is not None or p.support is None or not len(p.support):
            continue
        near = np.abs(s - p.station) <= 0.5
        if near.sum() < 5:
            continue
        _, d_pole = curve.project(p.support.mean(0)[None])
        side = np.sign(d_pole[0] - np.median(d[near]))
        if side != 0:
            p.away = side * curve.left(np.array([p.station]))[0]


def reconstruct_guardrail(
    points: np.ndarray,
    trajectory: np.ndarray | None = None,
    config: ReconstructionConfig | None = None,
    **settings: Any,
) -> ReconstructedGuardrail:
    """Reconstruct one guardrail from its points (N, 3) world float64 (the points of that
    guardrail only) and, when known, the survey trajectory (M, 3) sensor positions (it tells
    which side of a pole the scanner saw, and orients the result along the drive).

    `config` holds every step's settings (defaults: `ReconstructionConfig()`); flat `settings`
    (`kind="pipe"`, `max_units=4`) are applied over it (`ReconstructionConfig.updated`)."""
    cfg = (config or ReconstructionConfig()).updated(**settings)
    kind = cfg.kind
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise ValueError("guardrail points contain NaN or infinite coordinates")
    traj = None if trajectory is None else np.asarray(trajectory, dtype=np.float64)[:, :3]

    curve = rail_curve(pts, traj, cfg.curve) if len(pts) >= 2 else None
    poles = detect_poles(pts, traj, curve, cfg.poles) if curve is not None else []
    units = split_units(pts, poles, curve, cfg.units) if len(poles) >= 2 else []
    stack = superimpose(units, cfg.superimpose) if units else None
    ref = next((u for u in units if stack is not None and u.index == stack.reference), None)

    result_kind = kind if kind != "auto" else "unknown"
    pipes = beam = None
    band = 0.0
    if ref is not None and stack is not None:
        pole_x = (float(ref.pole_local[0, 0]), float(ref.pole_local[1, 0]))
        r_pole = float(np.median([p.radius for p in poles]))
        is_beam, band = looks_like_beam(stack.points, pole_x, r_pole, cfg.band)
        if kind == "auto":
            result_kind = "beam" if is_beam else "pipe"
        if result_kind == "beam" and curve is not None:
            _posts_behind_beam(poles, pts, curve)
        detected = [p for p in poles if p.detected]
        if sum(p.fitted for p in detected) < 0.5 * len(detected):  # few arcs fix a radius
            # (a sparse scan's fits are noise): the kind's prior
            place_poles(poles, POLE_RADIUS_PRIOR[result_kind])
            r_pole = POLE_RADIUS_PRIOR[result_kind]
        else:
            place_poles(poles, r_pole)
        if result_kind == "pipe":
            z_axes = [
                _affine_apply(stack.transforms[u.index], u.pole_local)[:, 2]
                for u in units
                if u.index in stack.transforms
            ]
            plane_z = float(np.median(np.concatenate(z_axes)))
            pipes = reconstruct_pipes(stack.points, pole_x, r_pole, plane_z, cfg.pipes)
        else:
            beam = beam_section(stack.points, pole_x, r_pole, cfg.beams)

    placements = _placements(poles, units, stack, ref) if len(poles) >= 2 else []
    segments = cfg.mesh.pole_segments
    parts = [meshes.cylinder(p.base_point, p.top_point, p.radius, segments) for p in poles]
    world_pipes: list[dict] = []
    beam_world = None
    if pipes is not None:
        m, world_pipes = _pipe_mesh(pipes, placements, cfg.mesh.tube_segments)
        parts.append(m)
    if beam is not None and placements:
        path, across, up = _beam_path(beam, placements)
        parts.append(meshes.sweep_section(beam.section, path, across, up))
        beam_world = {
            "section": beam.section.tolist(),  # (u, v): along `across`, along `up`
            "path": path.tolist(),
            "across": across.tolist(),
            "up": up.tolist(),
        }
    V, F = meshes.merge(parts)
    spacing = pole_spacing(poles) if len(poles) >= 2 else float("nan")
    model = {
        "kind": result_kind,
        "poles": [p.to_dict() for p in poles],
        "unit_length": float(spacing) if np.isfinite(spacing) else None,
        "units": len(units),
        "units_stacked": stack.units_stacked if stack is not None else 0,
        "icp_residual": stack.residual if stack is not None else None,
        "band_height": float(band),
        "unit_model": {
            "pipes": pipes.to_dict() if pipes is not None else None,
            "beam": beam.to_dict() if beam is not None else None,
            "reference_frame": ref.frame.matrix.tolist() if ref is not None else None,
        },
        "placements": [A.tolist() for A in placements],
        "pipes": world_pipes,
        "beam": beam_world,
        "origin": (0.5 * (V.min(0) + V.max(0))).tolist() if len(V) else [0.0, 0.0, 0.0],
    }
    return ReconstructedGuardrail(
        kind=result_kind,
        poles=poles,
        units_stacked=stack.units_stacked if stack is not None else 0,
        icp_residual=stack.residual if stack is not None else float("nan"),
        pipes=pipes,
        beam=beam,
        vertices=V,
        faces=F,
        model=model,
        placements=placements,
        stack=stack,
        curve=curve,
    )


def export_guardrail(rg: ReconstructedGuardrail, out_dir: str | Path, name: str) -> dict[str, str]:
    """Write the assembled mesh as OUT_DIR/NAME.glb, .obj and .ply (atomic; glTF and PLY
    relative to `rg.model["origin"]`, see `meshes`); returns {format: path}."""
    return meshes.export_mesh(
        (rg.vertices, rg.faces), out_dir, name, np.asarray(rg.model["origin"], dtype=np.float64)
    )
