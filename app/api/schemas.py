"""Public shapes of store records shared by several routers (the `Public` variants of
full-stack-fastapi-template): what the API returns, never the password hash."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel

from app.store.models import Role, User


class UserPublic(BaseModel):
    id: int
    username: str
    role: Role
    is_active: bool
    created_at: datetime
    version: int

    @classmethod
    def of(cls, user: User) -> UserPublic:
        return cls(
            id=user.id,
            username=user.username,
            role=user.role,
            is_active=user.is_active,
            created_at=user.created_at,
            version=user.version,
        )
