"""Login sessions: one row per login, named by the signed token, checked on every request.

A token alone cannot be taken back before it expires; the session it names can. Logout ends
the session, a user may end their other sessions, and a change of password, role or active
flag ends all of that user's sessions (`app.store.users.update_user`). Ended sessions stay a
while for the record and are then forgotten.

Reading a session on every request must not make every GET a write: `last_seen_at` is moved
at most once per `LAST_SEEN_EVERY` per session, by a conditional UPDATE (of requests racing
past the check, one writes, the others change nothing).
"""

from __future__ import annotations

from datetime import datetime, timedelta

import sqlalchemy as sa
from sqlmodel import Session, col, select

from app.core.errors import NotFoundError
from app.store.db import commit
from app.store.models import AuthSession, utcnow

LAST_SEEN_EVERY = timedelta(seconds=60)
KEEP_ENDED = timedelta(days=30)  # ended or expired sessions are deleted after this


class EndReason:
    """Why a session ended (`AuthSession.end_reason`)."""

    logout = "logout"
    revoked = "revoked"  # by the user (another of their sessions) or an admin
    password = "password"
    role = "role"
    deactivated = "deactivated"
    changed = "user changed"  # any other change to the user record


def start_session(
    session: Session,
    user_id: int,
    lifetime: timedelta,
    client_address: str | None = None,
    user_agent: str | None = None,
) -> AuthSession:
    """Add a new session for the user (flushed, so it has its id); the caller commits."""
    now = utcnow()
    row = AuthSession(
        user_id=user_id,
        created_at=now,
        last_seen_at=now,
        expires_at=now + lifetime,
        client_address=(client_address or None) and client_address[:64],
        user_agent=(user_agent or None) and user_agent[:255],
    )
    session.add(row)
    session.flush()
    return row


def live_session(session: Session, session_id: int, user_id: int) -> AuthSession | None:
    """The user's session `session_id` if it has neither ended nor expired."""
    row = session.get(AuthSession, session_id)
    if row is None or row.user_id != user_id or row.ended_at is not None:
        return None
    return row if row.expires_at > utcnow() else None


def touch(session: Session, row: AuthSession) -> None:
    """Record that the session was used now, unless that was recorded less than a minute ago
    (then nothing is written); commits only when it wrote."""
    now = utcnow()
    if now - row.last_seen_at < LAST_SEEN_EVERY:
        return
    stale = now - LAST_SEEN_EVERY
    moved = session.execute(
        sa.update(AuthSession)
        .where(col(AuthSession.id) == row.id, col(AuthSession.last_seen_at) < stale)
        .values(last_seen_at=now)
    )
    commit(session)
    if moved.rowcount:
        row.last_seen_at = now


def live_sessions(session: Session, user_id: int) -> list[AuthSession]:
    """The user's sessions that have neither ended nor expired, newest first."""
    query = (
        select(AuthSession)
        .where(
            AuthSession.user_id == user_id,
            col(AuthSession.ended_at).is_(None),
            AuthSession.expires_at > utcnow(),
        )
        .order_by(col(AuthSession.created_at).desc(), col(AuthSession.id).desc())
    )
    return list(session.exec(query).all())


def end_session(session: Session, user_id: int, session_id: int, reason: str) -> AuthSession:
    """End one live session of the user (NotFoundError when it is not theirs or not live);
    the caller commits."""
    row = live_session(session, session_id, user_id)
    if row is None:
        raise NotFoundError(f"user {user_id} has no live session {session_id}")
    row.ended_at = utcnow()
    row.end_reason = reason
    session.add(row)
    return row


def end_user_sessions(session: Session, user_id: int, reason: str, keep: int | None = None) -> int:
    """End every live session of the user but `keep`; how many ended. The caller commits."""
    query = sa.update(AuthSession).where(
        col(AuthSession.user_id) == user_id, col(AuthSession.ended_at).is_(None)
    )
    if keep is not None:
        query = query.where(col(AuthSession.id) != keep)
    result = session.execute(query.values(ended_at=utcnow(), end_reason=reason))
    return int(result.rowcount or 0)


def forget_old_sessions(session: Session, now: datetime | None = None) -> int:
    """Delete sessions that ended or expired more than `KEEP_ENDED` ago; the caller commits."""
    before = (now or utcnow()) - KEEP_ENDED
    result = session.execute(
        sa.delete(AuthSession).where(
            sa.or_(col(AuthSession.ended_at) < before, col(AuthSession.expires_at) < before)
        )
    )
    return int(result.rowcount or 0)
