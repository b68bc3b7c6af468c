"""`/users`: admins create users, change roles and passwords, deactivate, see and end a user's
login sessions; anyone lists names."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from app.api.deps import Admin, CurrentLogin, CurrentUser, SessionDep
from app.api.errors import errors
from app.api.routes.auth import SessionPublic, SessionsEnded
from app.api.schemas import UserPublic
from app.api.types import Id
from app.store.audit import audit
from app.store.db import commit
from app.store.models import Role
from app.store.sessions import EndReason, end_session, end_user_sessions, live_sessions
from app.store.users import all_users, create_user, get_user, update_user

router = APIRouter(prefix="/users", tags=["users"], responses=errors(401))


class UserCreate(BaseModel):
    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=8, max_length=1024)
    role: Role = Role.annotator


class UserUpdate(BaseModel):
    role: Role | None = None
    password: str | None = Field(None, min_length=8, max_length=1024)
    is_active: bool | None = None


@router.get("", response_model=list[UserPublic])
def list_users(_: CurrentUser, session: SessionDep) -> list[UserPublic]:
    return [UserPublic.model_validate(u) for u in all_users(session)]


@router.post("", response_model=UserPublic, status_code=201, responses=errors(403, 409, 422))
def add_user(body: UserCreate, admin: Admin, session: SessionDep) -> UserPublic:
    """Create a user (admin only)."""
    return UserPublic.model_validate(
        create_user(session, body.username, body.password, body.role, admin.id)
    )


@router.patch("/{user_id}", response_model=UserPublic, responses=errors(403, 404, 409, 422))
def change_user(user_id: Id, body: UserUpdate, admin: Admin, session: SessionDep) -> UserPublic:
    """Change role, password or active flag (admin only); the user's tokens stop working. The
    last active admin cannot be demoted or deactivated (409)."""
    user = update_user(
        session,
        user_id,
        admin.id,
        role=body.role,
        password=body.password,
        is_active=body.is_active,
    )
    return UserPublic.model_validate(user)


@router.get("/{user_id}/sessions", response_model=list[SessionPublic], responses=errors(403, 404))
def list_user_sessions(
    user_id: Id, _: Admin, login: CurrentLogin, session: SessionDep
) -> list[SessionPublic]:
    """A user's live login sessions, newest first (admin only)."""
    rows = live_sessions(session, get_user(session, user_id).id)
    return [SessionPublic.of(row, login.session.id) for row in rows]


@router.delete("/{user_id}/sessions", response_model=SessionsEnded, responses=errors(403, 404))
def end_user_all_sessions(
    user_id: Id, admin: Admin, login: CurrentLogin, session: SessionDep
) -> SessionsEnded:
    """End every live session of a user (admin only; the admin's own current one stays)."""
    user = get_user(session, user_id)
    ended = end_user_sessions(session, user.id, EndReason.revoked, keep=login.session.id)
    audit(session, admin.id, "auth.revoke", "user", user.id, sessions=ended)
    commit(session)
    return SessionsEnded(ended=ended)


@router.delete("/{user_id}/sessions/{session_id}", status_code=204, responses=errors(403, 404))
def end_user_session(user_id: Id, session_id: Id, admin: Admin, session: SessionDep) -> None:
    """End one live session of a user (admin only)."""
    user = get_user(session, user_id)
    end_session(session, user.id, session_id, EndReason.revoked)
    audit(session, admin.id, "auth.revoke", "user", user.id, session_id=session_id)
    commit(session)
