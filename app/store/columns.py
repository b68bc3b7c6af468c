"""How the store's tables keep their columns: the types and the columns every table shares.

- Integer primary keys `id` (`Record`); `created_at` (`Created`), `updated_at` (`Timestamped`,
  refreshed on every UPDATE) and `version` (`Versioned`) come first in each table, in that order.
- Timestamps are timezone-aware UTC (`UTCDateTime`): naive datetimes are taken as UTC on write,
  and every datetime read back carries `tzinfo=UTC`, whatever the backend stores.
- Records a user edits carry `version: int`, wired as SQLAlchemy's `version_id_col`: every ORM
  UPDATE runs `... WHERE id = ? AND version = <version loaded>` and bumps it, so two writers
  starting from the same version cannot both win; the loser gets `StaleDataError`
  (`app.store.db` turns it into `ConflictError`). Label operations compare the client's version
  with the loaded one first; setting `version` by hand is honoured instead of the automatic bump.
- JSON dict columns are `MutableDict`s, so `job.config["x"] = 1` is saved like an assignment
  (top-level keys only; replace nested values whole).
- Enums are stored as their string values in a VARCHAR (no native enum, no CHECK), so a new
  member never needs a table rebuild; unknown strings are refused when written.
- References to a survey cascade (`ON DELETE CASCADE`, enforced: the engine turns SQLite's
  `foreign_keys` on); references to users become NULL.
"""

import enum
from datetime import UTC, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.ext.mutable import MutableDict
from sqlalchemy.orm import declared_attr
from sqlmodel import Field, SQLModel


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(sa.types.TypeDecorator[datetime]):
    """A datetime stored as UTC and always read back timezone-aware (SQLite keeps no offset)."""

    impl = sa.DateTime
    cache_ok = True

    def __init__(self) -> None:
        super().__init__(timezone=True)

    def process_bind_param(self, value: datetime | None, dialect: sa.Dialect) -> datetime | None:
        if value is None:
            return None
        value = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: sa.Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def enum_type(enum_cls: type[enum.StrEnum]) -> sa.Enum:
    return sa.Enum(
        enum_cls,
        native_enum=False,
        create_constraint=False,
        length=32,
        values_callable=lambda members: [m.value for m in members],
        validate_strings=True,
    )


JSONDict = MutableDict.as_mutable(sa.JSON(none_as_null=True))
JSONList = sa.JSON(none_as_null=True)


def sql_time(moment: datetime) -> str:
    """A UTC time as SQLAlchemy stores DATETIME on SQLite (what `UTCDateTime` reads back), for
    plain SQL statements."""
    return moment.astimezone(UTC).replace(tzinfo=None).strftime("%Y-%m-%d %H:%M:%S.%f")


class Record(SQLModel):
    id: int | None = Field(default=None, primary_key=True)


class Created(Record):
    created_at: datetime = Field(default_factory=utcnow, sa_type=UTCDateTime, nullable=False)


class Timestamped(Created):
    updated_at: datetime = Field(
        default_factory=utcnow,
        sa_type=UTCDateTime,
        nullable=False,
        sa_column_kwargs={"onupdate": utcnow},
    )


class Versioned(Timestamped):
    """Optimistic concurrency: `version` is the mapper's version_id_col (see module docstring)."""

    version: int = Field(default=1, nullable=False)

    @declared_attr  # type: ignore[misc]
    def __mapper_args__(cls) -> dict[str, Any]:  # noqa: N805
        return {"version_id_col": cls.__table__.c.version}


def user_fk(index: bool = False) -> Any:
    return Field(default=None, foreign_key="user.id", ondelete="SET NULL", index=index)


def survey_fk() -> Any:
    return Field(foreign_key="survey.id", ondelete="CASCADE", index=True)
