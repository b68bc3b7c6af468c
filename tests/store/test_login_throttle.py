"""Login throttling in the store: lock-outs that double per failure up to the cap, per kind of
key, forgotten after a quiet window, cleared by a success."""

from __future__ import annotations

from datetime import timedelta

from sqlmodel import Session, select

from app.store.login_throttle import (
    ThrottlePolicy,
    clear,
    current_lockout,
    login_keys,
    record_failure,
)
from app.store.models import LoginThrottle, utcnow

POLICY = ThrottlePolicy(free_failures=5, address_free_failures=20, max_delay_s=900)


def test_delays_double_from_the_free_failures_up_to_the_cap() -> None:
    delays = [POLICY.delay_s("user", n) for n in range(1, 17)]
    assert delays == [0, 0, 0, 0, 1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 900, 900]
    assert POLICY.delay_s("address", 19) == 0 and POLICY.delay_s("address", 21) == 2
    assert POLICY.delay_s("user", 10**6) == 900  # no overflow however long a guesser goes on


def _failures(session: Session, keys, times: int) -> list:
    started = []
    for _ in range(times):
        started.append(record_failure(session, keys, POLICY))
        session.commit()
    return started


def test_each_failure_past_the_free_ones_locks_its_key_longer(session: Session) -> None:
    keys = login_keys("ann", "10.0.0.7")
    started, lengths = [], []
    for _ in range(7):
        started.append(_failures(session, keys, 1)[0])
        row = session.exec(select(LoginThrottle).where(LoginThrottle.kind == "user")).one()
        if row.locked_until is not None:
            lengths.append((row.locked_until - row.last_failure_at).total_seconds())
    assert [len(s) for s in started] == [0, 0, 0, 0, 1, 1, 1]  # the name only: 7 < 20
    assert lengths == [1, 2, 4]
    lock = current_lockout(session, keys)
    assert (lock.kind, lock.key, lock.failures) == ("user", "ann", 7)
    assert current_lockout(session, login_keys("bob", "10.0.0.8")) is None


def test_a_success_clears_the_name_not_the_address(session: Session) -> None:
    keys = login_keys("ann", "10.0.0.7")
    _failures(session, keys, 6)
    clear(session, keys[0])
    session.commit()
    assert current_lockout(session, keys) is None
    rows = session.exec(select(LoginThrottle.kind, LoginThrottle.failures)).all()
    assert rows == [("address", 6)]


def test_failures_are_forgotten_a_quiet_window_after_the_last_lock_out(session: Session) -> None:
    keys = login_keys("ann", None)
    _failures(session, keys, 6)  # locked for 2 s
    row = session.exec(select(LoginThrottle)).one()
    row.last_failure_at = utcnow() - POLICY.window - timedelta(seconds=5)
    row.locked_until = utcnow() - POLICY.window + timedelta(seconds=5)  # inside the window
    session.add(row)
    session.commit()
    _failures(session, keys, 1)
    assert session.exec(select(LoginThrottle.failures)).one() == 7  # not quiet long enough
    row = session.exec(select(LoginThrottle)).one()
    row.last_failure_at = row.locked_until = utcnow() - POLICY.window - timedelta(seconds=5)
    session.add(row)
    session.commit()
    _failures(session, keys, 1)
    assert session.exec(select(LoginThrottle.failures)).one() == 1  # a new count


def test_stale_keys_are_dropped(session: Session) -> None:
    _failures(session, login_keys("old", None), 1)
    row = session.exec(select(LoginThrottle)).one()
    row.last_failure_at = utcnow() - POLICY.window - timedelta(minutes=1)
    session.add(row)
    session.commit()
    _failures(session, login_keys("new", None), 1)
    assert session.exec(select(LoginThrottle.key)).all() == ["new"]
