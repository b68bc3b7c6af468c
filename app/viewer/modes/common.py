"""What the review modes share: role checks against the store (a user's role may change while
the viewer is open), picking a point with a click ray (viser point clouds have no per-point click
events), even subsampling for the browser and colour legends."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from app.core.errors import PermissionDeniedError
from app.store.models import Role, User
from app.store.users import has_role

if TYPE_CHECKING:
    from app.viewer.session import ViewerSession

PICK_ANGLE = 0.01  # rad: a click selects points within this angle of its ray ...
PICK_MIN_RADIUS = 0.15  # m: ... or this distance, whichever is larger


def checked_user(session: ViewerSession, role: Role, what: str) -> User:
    """The session's user, re-read from the store, when still active with at least `role`."""
    with session.db() as db:
        user = db.get(User, session.user_id)
    if user is None or not user.is_active:
        raise PermissionDeniedError(f"user {session.username!r} is no longer active")
    if not has_role(user, role):
        raise PermissionDeniedError(
            f"user {session.username!r} is {user.role.value}; {what} needs a {role.value}"
        )
    return user


def may(session: ViewerSession, role: Role) -> bool:
    """Whether the session's user has `role` now (to grey out buttons; writes check again)."""
    with session.db() as db:
        user = db.get(User, session.user_id)
    return user is not None and user.is_active and has_role(user, role)


def pick_on_ray(
    points: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    angle: float = PICK_ANGLE,
    min_radius: float = PICK_MIN_RADIUS,
) -> int:
    """Index of the nearest point (along the click ray) lying close to the ray, -1 for none:
    point clouds have no per-point click events in viser, so picking happens here."""
    if not len(points):
        return -1
    d = np.asarray(direction, dtype=np.float64)
    norm = np.linalg.norm(d)
    if not norm > 0:
        return -1
    d = d / norm
    rel = np.asarray(points, dtype=np.float64) - np.asarray(origin, dtype=np.float64)
    t = rel @ d
    perp2 = np.einsum("ij,ij->i", rel, rel) - t * t
    radius = np.maximum(min_radius, t * angle)
    near = np.flatnonzero((t > 0) & (perp2 <= radius * radius))
    if not len(near):
        return -1
    return int(near[np.argmin(t[near])])


def evenly(indices: np.ndarray, cap: int) -> np.ndarray:
    """At most `cap` of `indices`, evenly spread (the same subset every time)."""
    if len(indices) <= cap:
        return indices
    return indices[np.linspace(0, len(indices) - 1, cap).astype(np.int64)]


def swatch(rgb: Sequence[int]) -> str:
    r, g, b = (int(v) for v in rgb)
    return (
        '<span style="display:inline-block;width:0.9em;height:0.9em;margin-right:0.4em;'
        f'vertical-align:middle;background:rgb({r},{g},{b})"></span>'
    )


def legend_html(entries: Sequence[tuple[str, Sequence[int]]]) -> str:
    rows = "".join(f"<div>{swatch(rgb)}{name}</div>" for name, rgb in entries)
    return f'<div style="font-size:0.8em;padding:0 0.5em">{rows}</div>'
