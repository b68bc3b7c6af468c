"""Relay one browser websocket to the loopback viser server, frame for frame.

The browser talks to FastAPI (which checked its login); FastAPI dials viser on 127.0.0.1 with
the same `viser-v<version>` subprotocol and pumps binary frames both ways until either side
closes, then closes the other with the same code. Nothing is decoded or buffered here: viser's
frames are already batched and compressed. An optional `until` ends the relay from outside
(the login session behind it ended) with the close code and reason it returns.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Coroutine
from typing import Any

import websockets
from starlette.websockets import WebSocket, WebSocketDisconnect
from websockets.asyncio.client import ClientConnection, connect

UPSTREAM_OPEN_TIMEOUT = 10.0  # seconds
UNSENDABLE_CODES = {1005, 1006, 1015}  # reserved: they describe a close, never go on the wire


async def relay(
    browser: WebSocket,
    upstream_url: str,
    subprotocol: str,
    until: Coroutine[Any, Any, tuple[int, str]] | None = None,
) -> None:
    """Connect upstream, accept the browser with `subprotocol`, pump until one side closes or
    `until` returns (code, reason) to close both with."""
    try:
        upstream = await connect(
            upstream_url,
            subprotocols=[subprotocol],
            max_size=None,  # viser sends whole point clouds in one frame
            compression=None,  # loopback: deflating megabytes of floats only costs time
            open_timeout=UPSTREAM_OPEN_TIMEOUT,
            ping_interval=None,
        )
    except (OSError, TimeoutError, websockets.exceptions.WebSocketException):
        if until is not None:
            until.close()
        await browser.close(code=1011, reason="viewer unavailable")
        return
    await browser.accept(subprotocol=subprotocol)
    down = asyncio.create_task(_downstream(upstream, browser))
    up = asyncio.create_task(_upstream(browser, upstream))
    stop = asyncio.create_task(until) if until is not None else None
    tasks = [t for t in (down, up, stop) if t is not None]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        ended = _result(stop)
        await upstream.close(*(ended or ()))
        code, reason = ended or (upstream.close_code, upstream.close_reason or "")
        if code is None or code in UNSENDABLE_CODES:  # viser's code when it closed first
            code = 1000
        with contextlib.suppress(RuntimeError, WebSocketDisconnect, OSError):
            await browser.close(code=code, reason=reason)


def _result(task: asyncio.Task | None) -> tuple[int, str] | None:
    """What a finished `until` task returned; None when it did not finish."""
    if task is None or not task.done() or task.cancelled() or task.exception() is not None:
        return None
    return task.result()


async def _downstream(upstream: ClientConnection, browser: WebSocket) -> None:
    with contextlib.suppress(websockets.exceptions.ConnectionClosed):
        async for message in upstream:
            if isinstance(message, bytes):
                await browser.send_bytes(message)
            else:
                await browser.send_text(message)


async def _upstream(browser: WebSocket, upstream: ClientConnection) -> None:
    while True:
        message = await browser.receive()
        if message["type"] == "websocket.disconnect":
            return
        data = message.get("bytes")
        if data is None:
            data = message.get("text")
        if data is not None:
            await upstream.send(data)
