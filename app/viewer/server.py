"""The viser server behind the login.

viser runs its own thread and event loop and serves its page and websocket on one port; it has
no notion of users. So it listens on 127.0.0.1 only (never another address), and the only way in
from outside is the FastAPI relay at `/viewer/ws`, which checks the login first and files a
ticket naming the user (see `app.viewer.tickets`). The first thing viser does with a new
websocket, before it sends a byte, is run its low-level connect callbacks: ours reads the
ticket's nonce from the request path of that very connection and takes the ticket, or closes the
connection (1008). viser reports the client to the app only later (after its first camera
message), and then the session starts with the ticket taken at the door.

The server also owns what clients share: the open surveys (`SurveyViews`) and the label feed
that keeps them in step with the store.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
from typing import Any

import viser
from sqlalchemy.engine import Engine

from app.core.settings import Settings
from app.viewer.label_feed import LabelChange, LabelFeed, ReviewChange
from app.viewer.session import ViewerSession
from app.viewer.survey_view import SurveyViews
from app.viewer.tickets import Ticket, TicketRegistry, nonce_of

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
VISER_SUBPROTOCOL = f"viser-v{viser.__version__}"


class ViewerServer:
    def __init__(self, settings: Settings, engine: Engine):
        self.settings = settings
        self.engine = engine
        self.tickets = TicketRegistry()
        self.views = SurveyViews(engine, settings.cache_dir, settings.viewer_overview_points)
        self.sessions: dict[int, ViewerSession] = {}
        self._admitted: dict[int, Ticket] = {}  # client id -> its ticket, until its session starts
        self._sessions_lock = threading.Lock()
        self.viser: viser.ViserServer | None = None
        self.feed: LabelFeed | None = None

    def start(self) -> ViewerServer:
        # viser prints its own address whatever `verbose` says; that loopback port serves an
        # empty scene without a login, so only the app's address may reach the operator
        with contextlib.redirect_stdout(io.StringIO()):
            self.viser = viser.ViserServer(
                host=LOOPBACK, port=self.settings.viewer_port, verbose=False
            )
        websock = self.viser._websock_server  # runs these before any message goes out
        websock.on_client_connect(self._admit)
        websock.on_client_disconnect(self._forget_admission)
        self.viser.on_client_connect(self._on_connect)
        self.viser.on_client_disconnect(self._on_disconnect)
        self.feed = LabelFeed(
            self.engine, self._on_label_changes, on_reviews=self._on_review_changes
        ).start()
        log.debug("viewer: viser listens on %s:%d (loopback only)", LOOPBACK, self.port)
        return self

    def stop(self) -> None:
        if self.feed is not None:
            self.feed.stop()
        with self._sessions_lock:
            sessions = list(self.sessions.values())
            self.sessions.clear()
        for session in sessions:
            session.close()
        if self.viser is not None:
            self.viser.stop()

    @property
    def port(self) -> int:
        assert self.viser is not None, "the viewer is not started"
        return self.viser.get_port()

    @property
    def upstream_url(self) -> str:
        return f"ws://{LOOPBACK}:{self.port}/"

    def issue_ticket(
        self,
        user_id: int,
        username: str,
        survey_id: int | None,
        mode: str | None = None,
        area_id: int | None = None,
    ) -> str:
        return self.tickets.issue(Ticket(user_id, username, survey_id, mode, area_id))

    def labels_written(self) -> None:
        """Someone wrote pillar labels or review decisions (clutter, guardrail slices and
        models): have open views and modes update now, not at the next poll."""
        if self.feed is not None:
            self.feed.wake()

    # --- viser callbacks ----------------------------------------------------------------------

    async def _admit(self, client: Any) -> None:
        """On viser's event loop, as a websocket opens and before viser sends anything on it:
        take the ticket its request path names, or close it (policy violation)."""
        connection = self._connection_of(client.client_id)
        request = getattr(connection, "request", None)
        ticket = self.tickets.take(nonce_of(request.path)) if request is not None else None
        if ticket is None:
            log.warning("viewer: client %s came without a ticket; closing", client.client_id)
            if connection is not None:
                await connection.close(1008, "log in through /viewer")
            return
        with self._sessions_lock:
            self._admitted[client.client_id] = ticket

    def _forget_admission(self, client: Any) -> None:
        with self._sessions_lock:
            self._admitted.pop(client.client_id, None)

    async def _on_connect(self, client: viser.ClientHandle) -> None:
        """On viser's event loop, once the client sent its first camera: start its session
        with the ticket it was admitted with (a client without one was closed at the door)."""
        with self._sessions_lock:
            ticket = self._admitted.pop(client.client_id, None)
        if ticket is None:
            return
        session = ViewerSession(self, client, ticket)
        with self._sessions_lock:
            self.sessions[client.client_id] = session
        session.start()

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._sessions_lock:
            session = self.sessions.pop(client.client_id, None)
        if session is not None:
            session.close()

    def _connection_of(self, client_id: int) -> Any:
        """viser's websockets ServerConnection of a client (kept while the client is live)."""
        assert self.viser is not None
        return self.viser._websock_server._live_connections.get(client_id)

    # --- label feed ---------------------------------------------------------------------------

    def _on_label_changes(self, changes: list[LabelChange]) -> None:
        for change in changes:
            view = self.views.get(change.survey_id)
            if view is None:
                continue
            if change.model_replaced:
                view.load_all()
            elif len(change.human_cells):
                view.refresh_human(change.human_cells)

    def _on_review_changes(self, changes: list[ReviewChange]) -> None:
        """Review writes (anyone's): each session on the survey passes them to its mode."""
        with self._sessions_lock:
            sessions = list(self.sessions.values())
        for change in changes:
            for session in sessions:
                view = session.view
                if view is not None and view.survey_id == change.survey_id:
                    session.review_changed(change.survey_id, frozenset(change.actions))
