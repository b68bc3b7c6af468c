"""Request dependencies (the `api/deps.py` of full-stack-fastapi-template).

- `SessionDep`: one database session per request on the app's engine; routes commit.
- `CurrentUser`: the user of a valid bearer token (`Authorization: Bearer ...`) whose login
  session is still live (checked on every request: logout and revocation take effect at once).
  The login cookie is accepted too, but only for reads (GET/HEAD) and websockets, so a page on
  another site can never make a logged-in browser write. `CurrentLogin`: the user and the
  session together (for the routes that manage sessions).
- `Annotator`, `Reviewer`, `Admin`: `CurrentUser` with at least that role (roles nest).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm.exc import StaleDataError
from sqlmodel import Session

from app.api.disk_space import is_disk_full
from app.core.errors import PermissionDeniedError
from app.core.security import TokenSigner
from app.core.settings import Settings
from app.store.db import as_conflict
from app.store.models import AuthSession, Role, User
from app.store.sessions import live_session, touch
from app.store.users import has_role

log = logging.getLogger(__name__)
TOKEN_COOKIE = "mmsclean_token"
SAFE_METHODS = {"GET", "HEAD"}


def wake_viewer(request: Request) -> None:
    """After a label or review write: open viewers follow it now, not at the next poll of their
    feed (`app.viewer.label_feed`, which also sees writes from other processes)."""
    viewer = getattr(request.app.state, "viewer", None)
    if viewer is not None:
        viewer.labels_written()


def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


def get_db(request: Request) -> Iterator[Session]:
    with Session(request.app.state.engine, expire_on_commit=False) as session:
        try:
            yield session
        except (StaleDataError, IntegrityError) as exc:
            session.rollback()
            conflict = as_conflict(exc)
            raise conflict or exc from exc


SessionDep = Annotated[Session, Depends(get_db)]
SettingsDep = Annotated[Settings, Depends(get_settings_dep)]


def token_of(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value:
        return value.strip()
    if request.method in SAFE_METHODS or request.scope.get("type") == "websocket":
        return request.cookies.get(TOKEN_COOKIE)
    return None


@dataclass(frozen=True)
class Login:
    user: User
    session: AuthSession


def login_from_token(session: Session, signer: TokenSigner, token: str | None) -> Login | None:
    """The active user and live session a token names, if its signature is valid (checked
    before any database read), the session has not ended and the user is unchanged since
    login. Marks the session as used (written at most once a minute)."""
    claims = signer.check(token) if token else None
    if claims is None:
        return None
    user = session.get(User, claims.user_id)
    if user is None or not user.is_active or user.version != claims.user_version:
        return None
    auth_session = live_session(session, claims.session_id, user.id)
    if auth_session is None:
        return None
    try:
        touch(session, auth_session)
    except Exception as exc:  # on a full disk reads go on; the session's last use waits
        if not is_disk_full(exc):
            raise
        session.rollback()
        log.warning("login session %d: last use not recorded, the disk is full", auth_session.id)
    return Login(user, auth_session)


def user_from_token(session: Session, signer: TokenSigner, token: str | None) -> User | None:
    """The user of `login_from_token`, or None."""
    login = login_from_token(session, signer, token)
    return None if login is None else login.user


def get_login(request: Request, session: SessionDep) -> Login:
    login = login_from_token(session, request.app.state.token_signer, token_of(request))
    if login is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            detail="not logged in: send Authorization: Bearer <token> from POST /auth/login",
            headers={"WWW-Authenticate": "Bearer"},
        )
    return login


CurrentLogin = Annotated[Login, Depends(get_login)]


def get_current_user(login: CurrentLogin) -> User:
    return login.user


CurrentUser = Annotated[User, Depends(get_current_user)]


def require(role: Role):
    def dependency(user: CurrentUser) -> User:
        if not has_role(user, role):
            raise PermissionDeniedError(
                f"user {user.username!r} is {user.role.value}; this needs the {role.value} role"
            )
        return user

    return dependency


Annotator = Annotated[User, Depends(require(Role.annotator))]
Reviewer = Annotated[User, Depends(require(Role.reviewer))]
Admin = Annotated[User, Depends(require(Role.admin))]
