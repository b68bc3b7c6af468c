"""`/users`: admins create users, change roles and passwords, deactivate; anyone lists names."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field
from sqlmodel import select

from app.api.deps import Admin, CurrentUser, SessionDep
from app.api.errors import errors
from app.api.schemas import UserPublic
from app.store.models import Role, User
from app.store.users import create_user, update_user

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
    return [UserPublic.of(u) for u in session.exec(select(User).order_by(User.id)).all()]


@router.post("", response_model=UserPublic, status_code=201, responses=errors(403, 409, 422))
def add_user(body: UserCreate, admin: Admin, session: SessionDep) -> UserPublic:
    """Create a user (admin only)."""
    return UserPublic.of(create_user(session, body.username, body.password, body.role, admin.id))


@router.patch("/{user_id}", response_model=UserPublic, responses=errors(403, 404, 409, 422))
def change_user(user_id: int, body: UserUpdate, admin: Admin, session: SessionDep) -> UserPublic:
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
    return UserPublic.of(user)
