"""`/auth`: log in for a bearer token (also set as an HttpOnly cookie for the viewer), log out,
who am I, and the user's own login sessions (list, revoke).

Every login is a server-side session (`app.store.sessions`) named in the signed token, so
logout and revocation take effect at once. Failed logins are throttled per user name and per
client address (`app.store.login_throttle`): 429 with `Retry-After` while locked out.
"""

from __future__ import annotations

import logging
import math
from datetime import datetime, timedelta

from fastapi import APIRouter, HTTPException, Request, Response, status
from pydantic import BaseModel, Field
from sqlmodel import Session, SQLModel

from app.api.deps import TOKEN_COOKIE, CurrentLogin, CurrentUser, SessionDep, SettingsDep
from app.api.errors import errors
from app.api.schemas import UserPublic
from app.api.types import Id
from app.core.security import TOKEN_LIFETIME_S
from app.core.settings import Settings
from app.store.audit import audit
from app.store.db import commit, write_transaction
from app.store.login_throttle import (
    Key,
    ThrottlePolicy,
    clear,
    current_lockout,
    login_keys,
    record_failure,
)
from app.store.models import AuthSession
from app.store.sessions import (
    EndReason,
    end_session,
    end_user_sessions,
    forget_old_sessions,
    live_sessions,
    start_session,
)
from app.store.users import authenticate

log = logging.getLogger(__name__)

router = APIRouter(prefix="/auth", tags=["auth"])


class LoginRequest(BaseModel):
    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=1024)


class Token(BaseModel):
    access_token: str
    token_type: str = "bearer"
    expires_in: int
    user: UserPublic


class SessionPublic(SQLModel):
    id: int
    created_at: datetime
    last_seen_at: datetime = Field(description="updated at most once a minute")
    expires_at: datetime
    client_address: str | None
    user_agent: str | None
    current: bool = Field(description="the session of the token that asked")

    @classmethod
    def of(cls, row: AuthSession, current_id: int | None) -> SessionPublic:
        return cls.model_validate(row, update={"current": row.id == current_id})


class SessionsEnded(BaseModel):
    ended: int = Field(description="how many sessions were ended")


def throttle_policy(settings: Settings) -> ThrottlePolicy:
    return ThrottlePolicy(
        free_failures=settings.login_free_failures,
        address_free_failures=settings.login_address_free_failures,
        window=timedelta(seconds=settings.login_window_s),
        first_delay_s=settings.login_first_delay_s,
        max_delay_s=settings.login_max_delay_s,
    )


def client_address(request: Request) -> str | None:
    return request.client.host if request.client else None


def refuse_if_locked(session: Session, keys: list[Key]) -> None:
    """429 with Retry-After while the user name or the address is locked out."""
    lock = current_lockout(session, keys)
    if lock is None:
        return
    retry = max(1, math.ceil(lock.retry_after_s()))
    log.warning("login refused: %s %r locked out for %d s", lock.kind, lock.key, retry)
    what = f"user {lock.key!r}" if lock.kind == "user" else f"address {lock.key}"
    raise HTTPException(
        status.HTTP_429_TOO_MANY_REQUESTS,
        f"too many failed logins for {what}; try again in {retry} s",
        headers={"Retry-After": str(retry)},
    )


def count_failure(session: Session, keys: list[Key], policy: ThrottlePolicy) -> None:
    """Count the failed login; audit and log each lock-out it starts."""
    with write_transaction(session):
        for lock in record_failure(session, keys, policy):
            seconds = round(lock.retry_after_s(), 3)
            entity_id = f"{lock.kind}:{lock.key}"[:64]
            audit(
                session,
                None,
                "auth.lockout",
                "login",
                entity_id,
                kind=lock.kind,
                key=lock.key,
                failures=lock.failures,
                seconds=seconds,
            )
            log.warning(
                "login: %s %r locked out for %.0f s after %d failed logins",
                lock.kind,
                lock.key,
                seconds,
                lock.failures,
            )
        commit(session)


@router.post("/login", response_model=Token, responses=errors(401, 422, 429))
def login(
    body: LoginRequest,
    request: Request,
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
) -> Token:
    """Exchange a username and password for a bearer token (valid 12 h) naming a new login
    session. After repeated failures the name or address is locked out for a while (429)."""
    address = client_address(request)
    keys = login_keys(body.username, address)
    refuse_if_locked(session, keys)
    user = authenticate(session, body.username, body.password)
    if user is None:
        count_failure(session, keys, throttle_policy(settings))
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong username or password")
    with write_transaction(session):
        clear(session, keys[0])
        forget_old_sessions(session)
        auth = start_session(
            session,
            user.id,
            timedelta(seconds=TOKEN_LIFETIME_S),
            client_address=address,
            user_agent=request.headers.get("user-agent"),
        )
        audit(session, user.id, "auth.login", "user", user.id, session_id=auth.id)
        commit(session)
    token = request.app.state.token_signer.issue(user.id, user.version, auth.id)
    response.set_cookie(
        TOKEN_COOKIE, token, max_age=TOKEN_LIFETIME_S, httponly=True, samesite="strict"
    )
    return Token(
        access_token=token, expires_in=TOKEN_LIFETIME_S, user=UserPublic.model_validate(user)
    )


@router.post("/logout", status_code=204, responses=errors(401))
def logout(login: CurrentLogin, response: Response, session: SessionDep) -> None:
    """End this login session (its token stops working at once) and forget the cookie."""
    end_session(session, login.user.id, login.session.id, EndReason.logout)
    audit(session, login.user.id, "auth.logout", "user", login.user.id, session_id=login.session.id)
    commit(session)
    response.delete_cookie(TOKEN_COOKIE)


@router.get("/me", response_model=UserPublic, responses=errors(401))
def me(user: CurrentUser) -> UserPublic:
    return UserPublic.model_validate(user)


@router.get("/sessions", response_model=list[SessionPublic], responses=errors(401))
def list_my_sessions(login: CurrentLogin, session: SessionDep) -> list[SessionPublic]:
    """The user's live login sessions, newest first; `current` marks the one asking."""
    rows = live_sessions(session, login.user.id)
    return [SessionPublic.of(row, login.session.id) for row in rows]


@router.delete("/sessions", response_model=SessionsEnded, responses=errors(401))
def end_my_other_sessions(login: CurrentLogin, session: SessionDep) -> SessionsEnded:
    """End every live session of the user except the one asking."""
    ended = end_user_sessions(session, login.user.id, EndReason.revoked, keep=login.session.id)
    audit(session, login.user.id, "auth.revoke", "user", login.user.id, sessions=ended)
    commit(session)
    return SessionsEnded(ended=ended)


@router.delete("/sessions/{session_id}", status_code=204, responses=errors(401, 404))
def end_my_session(
    session_id: Id, login: CurrentLogin, response: Response, session: SessionDep
) -> None:
    """End one of the user's live sessions (404 for any other id); ending the current one is
    a logout."""
    end_session(session, login.user.id, session_id, EndReason.revoked)
    audit(session, login.user.id, "auth.revoke", "user", login.user.id, session_id=session_id)
    commit(session)
    if session_id == login.session.id:
        response.delete_cookie(TOKEN_COOKIE)
