"""Login throttling: growing lock-outs after repeated failed logins, per user name and per
client address.

Each key (`("user", name)` or `("address", ip)`) counts its failed logins; a failure more than
`window` after the previous one (or after the end of its lock-out) starts the count again.
From the `free_failures`-th failure on, each failure locks the key for
`first_delay * 2**(failures - free_failures)`, capped at `max_delay` (defaults: 1 s, 2 s,
4 s, ... up to 15 min after 5 failures of one name within 15 min; an address, which many users
may share, after 20). While a key is locked every login
naming it is refused with 429 before any password is checked, so a guesser gets one try per
lock-out whatever it sends. A successful login clears its user name's count (not the
address's: one known account must not reset the count of a guesser behind the same address).

The counts live in the store, so a restart does not reset them. Attempts that arrive at the
same moment all pass the check before any of them is counted: the lock-out holds after at most
as many extra tries as the server runs requests in parallel.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import sqlalchemy as sa
from sqlmodel import Session, col, select

from app.store.models import LoginThrottle, utcnow

Key = tuple[str, str]  # (kind, key): ("user", "anna"), ("address", "10.0.0.7")


@dataclass(frozen=True)
class ThrottlePolicy:
    free_failures: int = 5  # per user name
    address_free_failures: int = 20  # per client address (many users may share one)
    window: timedelta = timedelta(minutes=15)
    first_delay_s: float = 1.0
    max_delay_s: float = 900.0

    def delay_s(self, kind: str, failures: int) -> float:
        """How long `failures` failures within the window lock a key of `kind` (0: not)."""
        free = self.address_free_failures if kind == "address" else self.free_failures
        if failures < free:
            return 0.0
        doublings = min(failures - free, 64)
        return min(self.first_delay_s * 2.0**doublings, self.max_delay_s)


@dataclass(frozen=True)
class Lockout:
    kind: str
    key: str
    failures: int
    until: datetime

    def retry_after_s(self, now: datetime | None = None) -> float:
        return max((self.until - (now or utcnow())).total_seconds(), 0.0)


def login_keys(username: str, address: str | None) -> list[Key]:
    keys = [("user", username[:255])]
    if address:
        keys.append(("address", address[:255]))
    return keys


def _rows(session: Session, keys: list[Key]) -> dict[Key, LoginThrottle]:
    clauses = [sa.and_(LoginThrottle.kind == k, LoginThrottle.key == v) for k, v in keys]
    rows = session.exec(select(LoginThrottle).where(sa.or_(*clauses))).all()
    return {(r.kind, r.key): r for r in rows}


def current_lockout(session: Session, keys: list[Key]) -> Lockout | None:
    """The lock-out that lasts longest among `keys`; None when none is locked now."""
    now = utcnow()
    locked = [
        Lockout(r.kind, r.key, r.failures, r.locked_until)
        for r in _rows(session, keys).values()
        if r.locked_until is not None and r.locked_until > now
    ]
    return max(locked, key=lambda lock: lock.until, default=None)


def record_failure(session: Session, keys: list[Key], policy: ThrottlePolicy) -> list[Lockout]:
    """Count a failed login against every key; the lock-outs it starts. Run it in a write
    transaction; the caller commits."""
    now = utcnow()
    rows = _rows(session, keys)
    started = []
    for kind, key in keys:
        row = rows.get((kind, key))
        if row is None:
            row = LoginThrottle(kind=kind, key=key, failures=0, last_failure_at=now)
        elif now - _quiet_since(row) > policy.window:
            row.failures = 0
        row.failures += 1
        row.last_failure_at = now
        delay = policy.delay_s(kind, row.failures)
        row.locked_until = now + timedelta(seconds=delay) if delay else None
        session.add(row)
        if row.locked_until is not None:
            started.append(Lockout(kind, key, row.failures, row.locked_until))
    _forget_stale(session, now, policy)
    return started


def _quiet_since(row: LoginThrottle) -> datetime:
    """The end of the key's last failure or lock-out, whichever is later: the count is
    forgotten only a whole window after that (a guesser who sits out the longest lock-out
    does not start over with free tries)."""
    if row.locked_until is None:
        return row.last_failure_at
    return max(row.last_failure_at, row.locked_until)


def clear(session: Session, key: Key) -> None:
    """Forget the failures of one key (a successful login clears its user name); the caller
    commits."""
    session.execute(
        sa.delete(LoginThrottle).where(
            col(LoginThrottle.kind) == key[0], col(LoginThrottle.key) == key[1]
        )
    )


def _forget_stale(session: Session, now: datetime, policy: ThrottlePolicy) -> None:
    """Drop keys that would start over anyway (see `_quiet_since`): the table holds recent
    failures only, however many names a guesser tries."""
    before = now - policy.window
    session.execute(
        sa.delete(LoginThrottle).where(
            col(LoginThrottle.last_failure_at) < before,
            sa.or_(
                col(LoginThrottle.locked_until).is_(None), col(LoginThrottle.locked_until) < before
            ),
        )
    )
