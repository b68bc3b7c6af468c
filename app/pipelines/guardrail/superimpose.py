"""Superimposing unit shapes (Matsumoto, Mori & Masuda, section 4.2).

Thin pipes get too few points from one pass to be reconstructed, but a guardrail repeats one
unit shape, so the units are stacked: each unit is first placed roughly by its own frame (both
poles and the points' plane line up), shifted in height and depth to match the reference unit
seen end-on (a pole whose foot was hidden puts its unit's frame too high), then registered
precisely with ICP (open3d point-to-point) onto the reference unit. "As many unit shapes as
possible are superimposed."

ICP on guardrails has one weak direction: rails and beams look the same when slid along
themselves, and only poles and vertical or diagonal pipes pin a unit along x. A registration
that moves a unit further than the rough alignment can be wrong by, or turns it, is therefore
rejected and the rough alignment kept; and by default ICP's move along x is dropped: on sparse
scans (a profile scanner's lines 10-25 cm apart) point-to-point ICP pulls a unit's scan lines
onto the reference's, a bias of up to half the line spacing, while the poles place the unit
along x to about a centimetre (measured on simulated surveys: ICP x error 1.5-4 cm on profile
scans against 0.3-3 cm from the poles; on dense scans both stay below 3 mm). When the scan
lines of two units are farther apart than the correspondence distance ICP finds no pairs at
all; such units keep the rough alignment.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.ndimage import gaussian_filter
from scipy.signal import correlate

from app.pipelines.guardrail.config import SuperimposeConfig
from app.pipelines.guardrail.units import Unit


@dataclass
class Stack:
    """Units superimposed in the reference unit's frame."""

    points: np.ndarray  # (N, 3) in the reference unit frame
    unit_of_point: np.ndarray  # (N,) Unit.index of each point
    reference: int  # Unit.index of the reference unit
    transforms: dict[int, np.ndarray] = field(default_factory=dict)  # unit frame -> ref frame
    rmse: dict[int, float] = field(default_factory=dict)  # ICP inlier RMSE per unit (m)
    fitness: dict[int, float] = field(default_factory=dict)  # ICP inlier share per unit
    accepted: dict[int, bool] = field(default_factory=dict)  # ICP kept (else rough only)

    @property
    def units_stacked(self) -> int:
        return len(self.transforms)

    @property
    def residual(self) -> float:
        """Median ICP inlier RMSE (m) of the units registered onto the reference."""
        r = [v for k, v in self.rmse.items() if k != self.reference and np.isfinite(v)]
        return float(np.median(r)) if r else 0.0


def _cloud(p: np.ndarray) -> o3d.geometry.PointCloud:
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(p, dtype=np.float64))
    return pc


def _rotation_deg(T: np.ndarray) -> float:
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def section_shift(
    source: np.ndarray,
    target: np.ndarray,
    max_dy: float,
    max_dz: float,
    bin_size: float = 0.01,
) -> tuple[float, float]:
    """Shift (dy, dz) in m that best lines up two units seen end-on (their (y, z) occupancy,
    cross-correlated): the rough alignment's answer to a unit whose frame is off because a
    pole's foot was hidden (a parked car, a kerb, the median barrier: the frame sits too high)
    or because posts and beam share its points unevenly (the plane offset moves)."""
    pad = np.array([max_dy, max_dz])  # room for every lag searched
    lo = np.minimum(source[:, 1:].min(0), target[:, 1:].min(0)) - pad
    hi = np.maximum(source[:, 1:].max(0), target[:, 1:].max(0)) + pad
    shape = np.ceil((hi - lo) / bin_size).astype(int) + 1

    def image(p: np.ndarray) -> np.ndarray:
        idx = np.floor((p[:, 1:] - lo) / bin_size).astype(int)
        im = np.zeros(shape)
        np.add.at(im, (idx[:, 0], idx[:, 1]), 1.0)
        im = gaussian_filter(im, 1.5)
        return im / max(np.linalg.norm(im), 1e-12)

    c = correlate(image(target), image(source), mode="full", method="fft")
    zero = np.array(shape) - 1  # index of lag (0, 0)
    ky, kz = int(round(max_dy / bin_size)), int(round(max_dz / bin_size))
    win = c[zero[0] - ky : zero[0] + ky + 1, zero[1] - kz : zero[1] + kz + 1]
    iy, iz = np.unravel_index(int(np.argmax(win)), win.shape)
    return float((iy - ky) * bin_size), float((iz - kz) * bin_size)


def superimpose(units: list[Unit], config: SuperimposeConfig | None = None) -> Stack:
    """Stack `units` (rough alignment: every unit in its own frame; then ICP onto the reference
    unit, by default the one with the most points). `max_units` keeps the reference and the
    units nearest to it along the rail (the paper's experiment on how many are needed)."""
    cfg = config or SuperimposeConfig()
    if not units:
        return Stack(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), -1)
    by_index = {u.index: u for u in units}
    ref = cfg.reference
    if ref is None:
        ref = max(units, key=lambda u: len(u.local)).index
    if ref not in by_index:
        raise ValueError(f"reference unit {ref} is not among the units")
    chosen = sorted(by_index, key=lambda i: (abs(i - ref), i))
    if cfg.max_units is not None:
        chosen = chosen[: max(1, cfg.max_units)]
    target = _cloud(by_index[ref].local)
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=cfg.icp_iterations)
    method = o3d.pipelines.registration.TransformationEstimationPointToPoint()
    stack = Stack(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), ref)
    parts, owners = [], []
    for i in sorted(chosen):
        u = by_index[i]
        T = np.eye(4)
        if i == ref:
            stack.rmse[i], stack.fitness[i], stack.accepted[i] = 0.0, 1.0, True
        else:
            src = _cloud(u.local)
            T0 = np.eye(4)
            if cfg.max_height_shift > 0.0 or cfg.max_depth_shift > 0.0:
                T0[1, 3], T0[2, 3] = section_shift(
                    u.local, by_index[ref].local, cfg.max_height_shift, cfg.max_depth_shift
                )
            res = o3d.pipelines.registration.registration_icp(
                src, target, cfg.icp_distance, T0, method, criteria
            )
            Tr = np.array(res.transformation)
            if cfg.keep_rough_x:
                Tr[0, 3] = 0.0
            ok = (
                np.linalg.norm(Tr[:3, 3] - T0[:3, 3]) <= cfg.max_shift
                and _rotation_deg(Tr) <= cfg.max_rotation_deg
                and res.fitness >= cfg.min_fitness
            )
            if ok:
                T = Tr
                stack.rmse[i], stack.fitness[i] = float(res.inlier_rmse), float(res.fitness)
            else:
                T = T0
                ev = o3d.pipelines.registration.evaluate_registration(
                    src, target, cfg.icp_distance, T0
                )
                stack.rmse[i], stack.fitness[i] = float(ev.inlier_rmse), float(ev.fitness)
            stack.accepted[i] = bool(ok)
        stack.transforms[i] = T
        parts.append(u.local @ T[:3, :3].T + T[:3, 3])
        owners.append(np.full(len(u.local), i, dtype=np.int64))
    stack.points = np.concatenate(parts)
    stack.unit_of_point = np.concatenate(owners)
    return stack
