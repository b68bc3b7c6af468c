"""A minimal viser client in Python, for tests and the viewer benchmark: it speaks viser's wire
format through the `/viewer/ws` relay.

Server -> client frames (viser.infra._infra._message_producer): 8 bytes msgpack size, 8 bytes
compressed size, zstd-compressed msgpack `{"messages": [...], "binaryBufferLengths": [...]}`,
then the binary buffers (numpy arrays), each 8-byte aligned; arrays in the messages are
placeholders `{"__binary_index": i, "dtype": "<f4"}`. Client -> server frames are plain msgpack
of one message dict with its `type`. viser treats a client as connected once it sent its first
camera (`ViewerCameraMessage`), so `hello()` sends one.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import time
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np
import viser
import zstandard
from websockets.asyncio.client import ClientConnection, connect

SUBPROTOCOL = f"viser-v{viser.__version__}"
_zstd = zstandard.ZstdDecompressor()


def _align(offset: int) -> int:
    return offset + (8 - offset % 8) % 8


def _fill(value: Any, buffers: list[np.ndarray]) -> Any:
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return buffers[value["__binary_index"]].view(np.dtype(value["dtype"]))
        return {k: _fill(v, buffers) for k, v in value.items()}
    if isinstance(value, list):
        return [_fill(v, buffers) for v in value]
    return value


def decode_frame(frame: bytes) -> list[dict[str, Any]]:
    """The messages of one server frame, arrays as numpy views."""
    size = int.from_bytes(frame[0:8], "little")
    compressed = int.from_bytes(frame[8:16], "little")
    payload = _zstd.decompress(frame[16 : 16 + compressed], max_output_size=size)
    body = msgspec.msgpack.decode(payload)
    buffers, offset = [], 16 + compressed
    raw = np.frombuffer(frame, dtype=np.uint8)
    for length in body.get("binaryBufferLengths") or []:
        offset = _align(offset)
        buffers.append(raw[offset : offset + length])
        offset += length
    return [_fill(m, buffers) for m in body["messages"]]


def camera_message(
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0),
    position: tuple[float, float, float] = (-10.0, -10.0, 10.0),
    width: int = 1280,
    height: int = 720,
) -> bytes:
    return msgspec.msgpack.encode(
        {
            "type": "ViewerCameraMessage",
            "wxyz": (1.0, 0.0, 0.0, 0.0),
            "position": position,
            "fov": 1.3,
            "near": 0.01,
            "far": 1000.0,
            "image_height": height,
            "image_width": width,
            "look_at": look_at,
            "up_direction": (0.0, 0.0, 1.0),
        }
    )


def click_message(
    origin: tuple[float, float, float], direction: tuple[float, float, float]
) -> bytes:
    """A plain left click whose camera ray is origin + t * direction (scene coordinates)."""
    return msgspec.msgpack.encode(
        {
            "type": "ScenePointerMessage",
            "event_type": "click",
            "ray_origin": origin,
            "ray_direction": direction,
            "screen_pos": [(0.5, 0.5)],
            "modifier": None,
        }
    )


def gui_set(uuid: str, value: Any) -> bytes:
    """What the browser sends when a GUI input changes (a button press sets True)."""
    return msgspec.msgpack.encode(
        {"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}}
    )


def button_press(uuid: str) -> bytes:
    return gui_set(uuid, True)


def is_point_cloud(message: dict[str, Any]) -> bool:
    return message.get("type") == "PointCloudMessage"


def is_color_update(message: dict[str, Any]) -> bool:
    return message.get("type") == "SceneNodeUpdateMessage" and "colors" in message.get(
        "updates", {}
    )


class WireClient:
    """One viser client connection; `received` keeps every decoded message in order."""

    def __init__(self, connection: ClientConnection):
        self.connection = connection
        self.received: list[tuple[float, dict[str, Any]]] = []  # (perf_counter, message)
        self._cursor = 0  # received[:_cursor] were looked at by wait_for

    @classmethod
    async def open(cls, url: str, token: str | None = None, **kwargs: Any) -> WireClient:
        headers = {"Cookie": f"mmsclean_token={token}"} if token else {}
        kwargs.setdefault("compression", None)  # "deflate" offers what browsers offer
        connection = await connect(
            url, subprotocols=[SUBPROTOCOL], additional_headers=headers, max_size=None, **kwargs
        )
        return cls(connection)

    async def hello(self, **camera: Any) -> None:
        await self.connection.send(camera_message(**camera))

    async def wait_for(
        self, predicate: Callable[[dict[str, Any]], bool], timeout: float
    ) -> tuple[float, dict[str, Any]]:
        """(arrival time, message) of the first message after the last one returned that
        matches `predicate` (one frame may carry several messages)."""
        deadline = time.monotonic() + timeout
        while True:
            while self._cursor < len(self.received):
                arrived, message = self.received[self._cursor]
                self._cursor += 1
                if predicate(message):
                    return arrived, message
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no matching viser message in time")
            frame = await asyncio.wait_for(self.connection.recv(), left)
            arrived = time.perf_counter()
            self.received.extend((arrived, message) for message in decode_frame(frame))

    async def send(self, frame: bytes) -> None:
        await self.connection.send(frame)

    def gui_uuid(self, label: str, kind: str = "GuiButtonMessage") -> str:
        """The uuid of a GUI element (of message type `kind`) this client was sent."""
        for _, message in self.received:
            if message.get("type") == kind and message["props"]["label"] == label:
                return message["uuid"]
        raise KeyError(f"no {kind} {label!r} received")

    async def close(self) -> None:
        await self.connection.close()


def run_coroutine(coroutine: Any) -> Any:
    """`asyncio.run` in a thread of its own: a test may run while another fixture (Playwright's
    sync API, used by the browser tests) keeps an event loop running in the main thread."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        return pool.submit(asyncio.run, coroutine).result()
