"""`/viewer`: viser's client page and its websocket relay, for logged-in users only.

viser listens on 127.0.0.1 (see `app.viewer.server`); the browser reaches it only through here.
`GET /viewer` serves viser's single-file client page (from the installed viser package) pointed
at our relay: viser's client connects to the URL in its `?websocket=` query parameter (else to
the page's own URL), so the page is served at `/viewer?websocket=ws(s)://<host>/viewer/ws?survey=N`
and a bare `/viewer` redirects there. `WebSocket /viewer/ws` checks the login (cookie, bearer
header or `token` query parameter) and the Origin BEFORE accepting, files a ticket naming the
user and relays frames to viser with the `viser-v<version>` subprotocol the browser offered.
While it relays it checks every `MMSCLEAN_VIEWER_SESSION_CHECK_S` that the login session is
still live: logout, revocation or a change to the user close the viewer too (1008).
"""

from __future__ import annotations

import asyncio
import html
from functools import cache
from pathlib import Path
from typing import Annotated
from urllib.parse import parse_qs, quote, urlencode, urlsplit

import viser
from fastapi import APIRouter, HTTPException, Query, Request, WebSocket, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlmodel import Session

from app.api.deps import (
    TOKEN_COOKIE,
    Login,
    SessionDep,
    login_from_token,
    token_of,
    user_from_token,
)
from app.api.errors import errors
from app.api.types import Id
from app.core.errors import ConfigError, NotFoundError
from app.core.limits import INT64_MAX
from app.store.sessions import live_session, touch
from app.store.surveys import get_survey, survey_exists
from app.store.users import get_user
from app.store.work_areas import get_area
from app.viewer.modes import MODES
from app.viewer.relay import relay

router = APIRouter(tags=["viewer"])

WS_PATH = "/viewer/ws"
LOGIN_PAGE = "/"
MODE_KEYS = tuple(m.key for m in MODES)
MODE_LIST = ", ".join(MODE_KEYS)
POLICY_VIOLATION = 1008  # websocket close code; before accept the client sees HTTP 403


@cache
def client_page() -> bytes:
    """viser's built client page (one self-contained HTML file)."""
    return (Path(viser.__file__).parent / "client" / "build" / "index.html").read_bytes()


def relay_url(
    request: Request, survey: int | None, mode: str | None = None, area: int | None = None
) -> str:
    """ws(s)://<the host the browser used>/viewer/ws[?survey=N][&mode=KEY][&area=ID]."""
    scheme = "wss" if request.url.scheme == "https" else "ws"
    host = request.headers.get("host") or request.url.netloc
    params = {"survey": survey, "mode": mode, "area": area}
    query = urlencode({k: v for k, v in params.items() if v is not None})
    return f"{scheme}://{host}{WS_PATH}{'?' + query if query else ''}"


def _relay_params(websocket_url: str) -> tuple[int | None, str | None, int | None]:
    """(survey, mode, area) of a relay URL the page was pointed at."""
    query = parse_qs(urlsplit(websocket_url).query)
    survey, area = (survey_number(query.get(k, [""])[0]) for k in ("survey", "area"))
    return survey, query.get("mode", [None])[0], area


def survey_number(text: str | None) -> int | None:
    """A survey id given as text, None unless it is one (digits only, at most 64 bits)."""
    return int(text) if text and text.isdigit() and int(text) <= INT64_MAX else None


@router.get(
    "/viewer",
    response_class=Response,  # HTML page or redirect; errors are JSON
    responses={
        200: {"description": "viser's client page", "content": {"text/html": {}}},
        303: {"description": "to the page pointed at the relay; to the login page (browsers)"},
        **errors(401, 404, 422),
    },
)
def viewer_page(
    request: Request,
    session: SessionDep,
    survey: Annotated[Id | None, Query(description="survey to open")] = None,
    mode: Annotated[str | None, Query(description="mode to open first: " + MODE_LIST)] = None,
    area: Annotated[Id | None, Query(description="work area (its id) to look at first")] = None,
    websocket: Annotated[str | None, Query(description="set by the redirect")] = None,
) -> Response:
    """The 3D viewer (viser's client page) for the logged-in user; it connects to
    `/viewer/ws`. Browsers without a login are sent to the login page."""
    user = user_from_token(session, request.app.state.token_signer, token_of(request))
    if user is None:
        if "text/html" in request.headers.get("accept", ""):
            query = f"?{request.url.query}" if request.url.query else ""
            back = quote(f"{request.url.path}{query}", safe="")
            return RedirectResponse(f"{LOGIN_PAGE}?next={back}", status.HTTP_303_SEE_OTHER)
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            detail="not logged in: log in on the dashboard first",
            headers={"WWW-Authenticate": "Bearer"},
        )
    if websocket is not None and survey is None and mode is None and area is None:
        survey, mode, area = _relay_params(websocket)
        mode = mode if mode in MODE_KEYS else None
    browser = "text/html" in request.headers.get("accept", "")
    if mode is not None and mode not in MODE_KEYS:
        message = f"unknown viewer mode {mode!r}; known: {MODE_LIST}"
        if browser:
            return _error_page(status.HTTP_422_UNPROCESSABLE_ENTITY, f"mode: {message}")
        raise ConfigError("mode", message)
    if survey is not None and not survey_exists(session, survey):
        if browser:
            return _error_page(status.HTTP_404_NOT_FOUND, f"Survey {survey} does not exist.")
        get_survey(session, survey)  # the API's 404
    if area is not None and survey is None:
        message = "a work area is opened on its survey: give survey too"
        if browser:
            return _error_page(status.HTTP_422_UNPROCESSABLE_ENTITY, f"area: {message}")
        raise ConfigError("area", message)
    if area is not None:
        try:
            get_area(session, survey, area)
        except NotFoundError:
            if not browser:
                raise  # the API's 404
            return _error_page(
                status.HTTP_404_NOT_FOUND, f"Survey {survey} has no work area {area}."
            )
    expected = relay_url(request, survey, mode, area)
    if websocket != expected:  # only ever point the page at our own relay
        return RedirectResponse(
            f"/viewer?websocket={quote(expected, safe='')}", status.HTTP_303_SEE_OTHER
        )
    return HTMLResponse(client_page(), headers={"Cache-Control": "no-store"})


def _error_page(code: int, message: str) -> HTMLResponse:
    """What a person who followed a link reads (scripts get the API's JSON detail)."""
    page = (
        '<!doctype html><html lang="en"><head><meta charset="utf-8"><title>mmsclean viewer'
        '</title><link rel="stylesheet" href="/assets/style.css"></head><body><main '
        'class="card"><h1>The viewer cannot open this</h1>'
        f'<p id="viewer-error">{html.escape(message)}</p>'
        '<p><a href="/#/surveys">Back to the surveys</a></p></main></body></html>'
    )
    return HTMLResponse(page, code, headers={"Cache-Control": "no-store"})


def _same_origin(websocket: WebSocket) -> bool:
    """A browser page from another origin (another port on this host counts) may not use the
    cookie to reach the viewer; clients that send no Origin are not browsers."""
    origin = websocket.headers.get("origin")
    if origin is None:
        return True
    return urlsplit(origin).netloc == websocket.headers.get("host")


def _token(websocket: WebSocket, query_token: str | None) -> str | None:
    """The `token` query parameter, a bearer header, or the login cookie."""
    scheme, _, value = websocket.headers.get("authorization", "").partition(" ")
    bearer = value.strip() if scheme.lower() == "bearer" else ""
    return query_token or bearer or websocket.cookies.get(TOKEN_COOKIE)


def _login(websocket: WebSocket, query_token: str | None) -> Login | None:
    """The logged-in user and session, when the survey asked for (if any) exists too."""
    app = websocket.app
    token = _token(websocket, query_token)
    with Session(app.state.engine, expire_on_commit=False) as session:
        login = login_from_token(session, app.state.token_signer, token)
        if login is None:
            return None
        survey = websocket.query_params.get("survey")
        if survey is None:
            return login
        number = survey_number(survey)
        exists = number is not None and survey_exists(session, number)
        return login if exists else None


def _still_logged_in(websocket: WebSocket, user_id: int, session_id: int) -> bool:
    """The relay's login session is live and its user active (marks the session as used)."""
    with Session(websocket.app.state.engine, expire_on_commit=False) as session:
        try:
            user = get_user(session, user_id)
        except NotFoundError:
            return False
        row = live_session(session, session_id, user_id)
        if not user.is_active or row is None:
            return False
        touch(session, row)
        return True


async def _until_logged_out(websocket: WebSocket, login: Login) -> tuple[int, str]:
    """Return (1008, reason) once the login session behind a relay has ended."""
    every = websocket.app.state.settings.viewer_session_check_s
    while True:
        await asyncio.sleep(every)
        alive = await run_in_threadpool(
            _still_logged_in, websocket, login.user.id, login.session.id
        )
        if not alive:
            return POLICY_VIOLATION, "login session ended"


@router.websocket(WS_PATH)
async def viewer_socket(websocket: WebSocket, token: str | None = None) -> None:
    """Relay to the loopback viser server, for a valid login only (refused before accept)."""
    viewer = getattr(websocket.app.state, "viewer", None)
    offered = [p for p in websocket.scope.get("subprotocols", []) if p.startswith("viser-v")]
    if viewer is None or not offered or not _same_origin(websocket):
        await websocket.close(code=POLICY_VIOLATION)
        return
    login = await run_in_threadpool(_login, websocket, token)
    if login is None:
        await websocket.close(code=POLICY_VIOLATION)
        return
    user = login.user
    survey = websocket.query_params.get("survey")
    mode = websocket.query_params.get("mode")
    area = survey_number(websocket.query_params.get("area")) if survey else None
    nonce = viewer.issue_ticket(
        user.id,
        user.username,
        int(survey) if survey else None,
        mode if mode in MODE_KEYS else None,
        area,
    )
    try:
        upstream = f"{viewer.upstream_url}?session={nonce}"
        await relay(websocket, upstream, offered[0], until=_until_logged_out(websocket, login))
    finally:
        viewer.tickets.revoke(nonce)
