"""Who may download which file: one rule for survey exports and job output files.

The exports hand out the product (cleaned and removed maps, guardrail meshes, pillar label
sets, the QA report) and are for reviewers. A job's folder holds the same kinds of file (its
maps, meshes, label arrays, overlays, checkpoints) next to its log and run report, so the rule
goes by the kind of file, not by the route: the same map is reviewer-only whether it comes from
`/surveys/{id}/exports/` or from `/jobs/{id}/files/`. Annotators may read logs and reports
(plain text, JSON); every other kind, including one not listed here, needs the reviewer role.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import PurePosixPath

from app.api.deps import CurrentUser
from app.core.errors import PermissionDeniedError
from app.store.models import Role, User
from app.store.users import has_role

OPEN_KINDS = frozenset({".log", ".txt", ".json"})  # job logs and run reports


def download_role(name: str) -> Role:
    """The least role that may download a file called `name` (a path is judged by its name)."""
    return Role.annotator if PurePosixPath(name).suffix.lower() in OPEN_KINDS else Role.reviewer


def may_download(user: User, name: str) -> bool:
    return has_role(user, download_role(name))


def check_download(user: User, name: str) -> None:
    """PermissionDeniedError (403) when `user` may not download `name`."""
    needed = download_role(name)
    if not has_role(user, needed):
        raise PermissionDeniedError(
            f"user {user.username!r} is {user.role.value}; {PurePosixPath(name).name} needs "
            f"the {needed.value} role (maps, meshes and label sets are for reviewers)"
        )


def downloader(name: str) -> Callable[[User], User]:
    """A route dependency: the current user, when they may download `name`."""

    def dependency(user: CurrentUser) -> User:
        check_download(user, name)
        return user

    return dependency
