"""Users: creation with a hashed password, authentication, the first admin."""

from __future__ import annotations

import re
from functools import cache

from sqlmodel import Session, func, select

from app.core.errors import ConfigError, ConflictError, NotFoundError
from app.core.security import hash_password, verify_password
from app.store.audit import audit
from app.store.db import commit, write_transaction
from app.store.models import Role, User
from app.store.sessions import EndReason, end_user_sessions

USERNAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MIN_PASSWORD_LENGTH = 8
ROLE_RANK = {Role.annotator: 1, Role.reviewer: 2, Role.admin: 3}


def has_role(user: User, needed: Role) -> bool:
    """Roles nest: a reviewer may do what an annotator may, an admin everything."""
    return ROLE_RANK[user.role] >= ROLE_RANK[needed]


def check_new_credentials(username: str, password: str) -> None:
    if not USERNAME.match(username):
        raise ConfigError(
            "username", "1-64 letters, digits, '_', '.' or '-', starting with a letter or digit"
        )
    if len(password) < MIN_PASSWORD_LENGTH:
        raise ConfigError("password", f"must have at least {MIN_PASSWORD_LENGTH} characters")


def all_users(session: Session) -> list[User]:
    """Every user, by id."""
    return list(session.exec(select(User).order_by(User.id)).all())


def get_user(session: Session, user_id: int) -> User:
    user = session.get(User, user_id)
    if user is None:
        raise NotFoundError(f"user {user_id} not found")
    return user


def get_user_by_name(session: Session, username: str) -> User | None:
    return session.exec(select(User).where(User.username == username)).first()


def create_user(
    session: Session, username: str, password: str, role: Role, created_by: int | None = None
) -> User:
    """Insert a user (ConflictError when the name is taken); commits."""
    check_new_credentials(username, password)
    if get_user_by_name(session, username) is not None:
        raise ConflictError(f"user {username!r} already exists")
    user = User(username=username, hashed_password=hash_password(password), role=Role(role))
    session.add(user)
    session.flush()
    audit(session, created_by, "user.create", "user", user.id, username=username, role=role)
    commit(session)
    session.refresh(user)
    return user


def authenticate(session: Session, username: str, password: str) -> User | None:
    """The active user with these credentials, or None (same answer for any failure)."""
    user = get_user_by_name(session, username)
    if user is None or not user.is_active:
        verify_password(password, _dummy_hash())  # same cost whether or not the name exists
        return None
    return user if verify_password(password, user.hashed_password) else None


def update_user(
    session: Session,
    user_id: int,
    by: int,
    *,
    role: Role | None = None,
    password: str | None = None,
    is_active: bool | None = None,
) -> User:
    """Change a user's role, password or active flag; every change ends their login sessions.

    The last active admin cannot lose the role or be deactivated: nobody could manage users
    then. Checked in the write's transaction, so two admins demoting each other at once
    cannot both succeed.
    """
    hashed = None if password is None else hash_password(password)  # slow: not under the lock
    with write_transaction(session):
        user = session.get(User, user_id, populate_existing=True)
        if user is None:
            raise NotFoundError(f"user {user_id} not found")
        demoted = role is not None and Role(role) != Role.admin
        loses_admin = user.role == Role.admin and user.is_active and (demoted or is_active is False)
        if loses_admin and admin_count(session) <= 1:
            raise ConflictError(
                f"user {user.username!r} is the last active admin; make another user admin first"
            )
        changes: dict[str, object] = {}
        if role is not None and role != user.role:
            user.role = Role(role)
            changes["role"] = str(role)
        if password is not None:
            check_new_credentials(user.username, password)
            user.hashed_password = hashed
            changes["password"] = "changed"
        if is_active is not None and is_active != user.is_active:
            user.is_active = is_active
            changes["is_active"] = is_active
        if changes:
            ended = end_user_sessions(session, user.id, _end_reason(changes))
            audit(session, by, "user.update", "user", user.id, **changes, sessions_ended=ended)
        commit(session)
    if changes:
        session.refresh(user)
    return user


def _end_reason(changes: dict[str, object]) -> str:
    """Why a change to a user ends their sessions (the strongest reason names it)."""
    if changes.get("is_active") is False:
        return EndReason.deactivated
    if "password" in changes:
        return EndReason.password
    return EndReason.role if "role" in changes else EndReason.changed


def admin_count(session: Session) -> int:
    query = select(func.count()).select_from(User).where(User.role == Role.admin)
    return int(session.exec(query.where(User.is_active)).one())


def ensure_first_admin(session: Session, password: str | None) -> User | None:
    """On a start with no admin and `MMSCLEAN_ADMIN_PASSWORD` set, create the user `admin`."""
    if not password or admin_count(session):
        return None
    existing = get_user_by_name(session, "admin")
    if existing is not None:  # an `admin` that lost its role or was deactivated: restore it
        return update_user(
            session, existing.id, existing.id, role=Role.admin, password=password, is_active=True
        )
    return create_user(session, "admin", password, Role.admin)


@cache
def _dummy_hash() -> str:
    return hash_password("not a real password")
