"""`/auth`: log in for a bearer token (also set as an HttpOnly cookie for the viewer), log out,
who am I."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, Response, status
from pydantic import BaseModel, Field

from app.api.deps import TOKEN_COOKIE, CurrentUser, SessionDep
from app.api.errors import errors
from app.api.schemas import UserPublic
from app.core.security import TOKEN_LIFETIME_S
from app.store.audit import audit
from app.store.db import commit
from app.store.users import authenticate

router = APIRouter(prefix="/auth", tags=["auth"])


class LoginRequest(BaseModel):
    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=1024)


class Token(BaseModel):
    access_token: str
    token_type: str = "bearer"
    expires_in: int
    user: UserPublic


@router.post("/login", response_model=Token, responses=errors(401, 422))
def login(body: LoginRequest, request: Request, response: Response, session: SessionDep) -> Token:
    """Exchange a username and password for a bearer token (valid 12 h)."""
    user = authenticate(session, body.username, body.password)
    if user is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong username or password")
    token = request.app.state.token_signer.issue(user.id, user.version)
    audit(session, user.id, "auth.login", "user", user.id)
    commit(session)
    response.set_cookie(
        TOKEN_COOKIE, token, max_age=TOKEN_LIFETIME_S, httponly=True, samesite="strict"
    )
    return Token(access_token=token, expires_in=TOKEN_LIFETIME_S, user=UserPublic.of(user))


@router.post("/logout", status_code=204, responses=errors(401))
def logout(user: CurrentUser, response: Response) -> None:
    """Forget the login cookie (bearer tokens simply expire)."""
    response.delete_cookie(TOKEN_COOKIE)


@router.get("/me", response_model=UserPublic, responses=errors(401))
def me(user: CurrentUser) -> UserPublic:
    return UserPublic.of(user)
