"""How moving things move: a path (polyline) and a speed plan integrated over time -> Motion.

The phantom paper stresses that phantoms vary with the object's speed: vehicles accelerate,
brake and stop at traffic lights, pedestrians walk slowly. A `SpeedPlan` covers cruising,
starting late, stopping at a light until it turns green, and accelerating again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.simulate.scene import Motion

MOTION_DT = 0.02  # seconds between motion samples (50 Hz; linear interpolation in between)


@dataclass(frozen=True)
class SpeedPlan:
    speed: float  # cruise speed, m/s
    start_delay: float = 0.0  # seconds standing still at the start of the simulation
    initial_speed: float | None = None  # speed at t0 (default: cruise speed unless delayed)
    accel: float = 2.0  # m/s^2 when speeding up
    decel: float = 3.0  # m/s^2 when braking
    stop_at: float | None = None  # path arc length of a stop line (red light)
    green_at: float | None = None  # time the light turns green


def integrate_speed(plan: SpeedPlan, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, arc length travelled) sampled every MOTION_DT from t0 to t1.

    A loop over time steps (a few thousand), not over points: braking for a stop line needs the
    state of the previous step.
    """
    times = np.arange(t0, t1 + MOTION_DT, MOTION_DT)
    s = np.zeros(len(times))
    v = plan.speed if plan.initial_speed is None else plan.initial_speed
    if plan.start_delay > 0:
        v = 0.0 if plan.initial_speed is None else v
    for i in range(1, len(times)):
        t = times[i - 1]
        target = plan.speed if t >= t0 + plan.start_delay else 0.0
        if plan.stop_at is not None and plan.green_at is not None and t < plan.green_at:
            remaining = plan.stop_at - s[i - 1]
            if remaining <= 0.05:
                target = 0.0
                v = 0.0 if remaining > -1.0 else v  # already past the line: keep going
            elif v * v / (2 * plan.decel) >= remaining - 0.05:
                target = 0.0
        if v < target:
            v = min(target, v + plan.accel * MOTION_DT)
        elif v > target:
            v = max(target, v - plan.decel * MOTION_DT)
        s[i] = s[i - 1] + v * MOTION_DT
    return times, s


def follow_path(path: np.ndarray, times: np.ndarray, travelled: np.ndarray) -> Motion:
    """Motion of a body whose ground centre runs along `path` (K,3), heading along the path,
    pitched with its slope."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.clip(travelled, 0.0, arc[-1])
    positions = np.stack([np.interp(s, arc, path[:, k]) for k in range(3)], -1)
    d = np.diff(path, axis=0)
    seg_heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    seg_pitch = np.arctan2(d[:, 2], np.maximum(np.linalg.norm(d[:, :2], axis=1), 1e-9))
    mids = 0.5 * (arc[1:] + arc[:-1])
    yaws = np.interp(s, mids, seg_heading)
    pitches = np.interp(s, mids, seg_pitch)
    return Motion(times, positions, yaws, pitches)


def path_motion(path: np.ndarray, plan: SpeedPlan, t0: float, t1: float) -> Motion:
    times, travelled = integrate_speed(plan, t0, t1)
    return follow_path(path, times, travelled)
