"""What the review modes share: role checks against the store (a user's role may change while
the viewer is open), picking the point a click means (`picking.pick_on_ray` with the click's
camera), even subsampling for the browser and colour legends."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from app.core.errors import PermissionDeniedError
from app.store.models import Role, User
from app.store.users import has_role
from app.viewer.picking import click_angle, pick_on_ray

TARGET_RGB = (220, 20, 60)  # red outline of what a mode points the user to (no class colour)

if TYPE_CHECKING:
    from viser import SceneClickEvent

    from app.viewer.session import ViewerSession


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


def pick_clicked(points: np.ndarray, event: SceneClickEvent, point_size: float) -> int:
    """Index of the shown point the click means (nearest the cursor on the surface drawn
    there, within a few pixels; `picking.pick_on_ray`), -1 for none."""
    angle = click_angle(event.client.camera)
    return pick_on_ray(points, event.ray_origin, event.ray_direction, angle, point_size)


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
