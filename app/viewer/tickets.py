"""Who is behind a viser client: one ticket per relayed websocket.

The viser server only ever sees connections from our relay on the loopback port, so it cannot
check a login itself. The relay checks the login, files a ticket under a random nonce and
connects upstream to `ws://127.0.0.1:<port>/?session=<nonce>`; when viser reports the new client
the viewer reads the nonce from that connection's request path and takes the ticket. A nonce
names exactly one connection, so two users connecting at once can never be mixed up, and a
client that arrives without a valid nonce (someone else on the machine dialling the loopback
port) gets no session.
"""

from __future__ import annotations

import secrets
import threading
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

NONCE_PARAM = "session"


@dataclass(frozen=True)
class Ticket:
    user_id: int
    username: str
    survey_id: int | None  # None: the viewer picks the first survey
    mode: str | None = None  # a Mode.key to open first (the dashboard's links); None: the first
    area_id: int | None = None  # a work area of the survey to look at first (its id)


class TicketRegistry:
    """nonce -> Ticket, filed by the relay before it dials viser, taken once by the viewer."""

    def __init__(self) -> None:
        self._tickets: dict[str, Ticket] = {}
        self._lock = threading.Lock()

    def issue(self, ticket: Ticket) -> str:
        nonce = secrets.token_urlsafe(24)
        with self._lock:
            self._tickets[nonce] = ticket
        return nonce

    def take(self, nonce: str | None) -> Ticket | None:
        """The ticket filed under `nonce`, removed so it cannot be used twice."""
        if not nonce:
            return None
        with self._lock:
            return self._tickets.pop(nonce, None)

    def revoke(self, nonce: str) -> None:
        """Forget a ticket nobody took (the upstream connection failed or closed early)."""
        with self._lock:
            self._tickets.pop(nonce, None)

    def __len__(self) -> int:
        with self._lock:
            return len(self._tickets)


def nonce_of(request_path: str) -> str | None:
    """The nonce in an upstream request path such as `/?session=abc`."""
    values = parse_qs(urlsplit(request_path).query).get(NONCE_PARAM)
    return values[0] if values else None
