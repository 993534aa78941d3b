"""A minimal headless viser client speaking the real websocket protocol (for tests and studies).

Wire format (viser 1.1.1, `viser/infra/_infra.py`): the client sends one msgpack dict per
websocket message, {"type": <message class name>, **fields}. The server sends frames
    [u64 inner size][u64 zstd size][zstd(msgpack {"messages": [...], ...})][padded raw buffers],
whose messages are dicts with a "type" key (numpy arrays are replaced by binary placeholders).
A client counts as connected (on_client_connect fires) only after its first ViewerCameraMessage.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np
import viser
import websockets
import zstandard

from flipviz.data.cameras import look_at
from flipviz.viz.app.poses import to_viser_pose

_zstd = zstandard.ZstdDecompressor()


def decode_frame(raw: bytes) -> list[dict]:
    """Server frame -> list of message dicts, their binary buffers (viser's {"__binary_index", "dtype"}
    placeholders) resolved to bytes: the zstd msgpack, then each buffer 8-byte aligned (viser/infra)."""
    inner_size = int.from_bytes(raw[0:8], "little")
    comp_size = int.from_bytes(raw[8:16], "little")
    inner = msgspec.msgpack.decode(_zstd.decompress(raw[16 : 16 + comp_size], max_output_size=inner_size))
    buffers, at = [], 16 + comp_size
    for n in inner.get("binaryBufferLengths") or ():
        at += (8 - at % 8) % 8
        buffers.append(bytes(raw[at : at + n]))
        at += n

    def resolve(v):
        if isinstance(v, dict):
            return (
                buffers[v["__binary_index"]]
                if "__binary_index" in v and "dtype" in v
                else {k: resolve(x) for k, x in v.items()}
            )
        return [resolve(x) for x in v] if isinstance(v, list) else v

    return [resolve(m) for m in inner["messages"]]


def wxyz_look_at(position: np.ndarray, target: np.ndarray) -> tuple[float, ...]:
    """Quaternion (w, x, y, z) of viser's (OpenCV) camera at `position` looking at `target`, z up."""
    return tuple(float(v) for v in to_viser_pose(look_at(position, target))[0])


async def until(cond: Callable[[], object], what: str | Callable[[], object], timeout: float = 60.0) -> None:
    """Wait (on the event loop, the client's reader going on) until the app's side of a change holds;
    `what` names it (a callable: what the app shows when the wait fails)."""
    t = time.monotonic()
    while not cond():
        assert time.monotonic() - t < timeout, what() if callable(what) else what
        await asyncio.sleep(0.05)


class ViserTestClient:
    """Connects, records every message it receives, and sends camera / GUI / gizmo messages."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.ws: Any = None
        self.messages: list[dict] = []
        self.gui: dict[str, dict] = {}  # label -> creation message (the latest one)
        self.frames: list[tuple[float, int, list[str]]] = []  # (arrival time, bytes, message types) per frame
        self._reader: asyncio.Task | None = None
        self._new = asyncio.Event()

    async def __aenter__(self) -> ViserTestClient:
        self.ws = await websockets.connect(
            self.url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None, compression=None
        )
        self._reader = asyncio.create_task(self._read())
        return self

    async def __aexit__(self, *exc) -> None:
        if self._reader is not None:
            self._reader.cancel()
        await self.ws.close()

    async def _read(self) -> None:
        try:
            async for raw in self.ws:
                msgs = decode_frame(raw)
                self.frames.append((time.monotonic(), len(raw), [m.get("type", "?") for m in msgs]))
                for m in msgs:
                    self.messages.append(m)
                    props = m.get("props")
                    labelled = "uuid" in m and isinstance(props, dict) and props.get("label")
                    if labelled and m["type"] != "GuiFolderMessage":  # (a folder's label may be an input's: "Scene")
                        self.gui[props["label"]] = m
                self._new.set()
        except websockets.ConnectionClosed:
            pass

    def visible_nodes(self) -> set[str]:
        """The scene nodes this browser draws now: added, not removed, and neither they nor a parent
        hidden (SetSceneNodeVisibilityMessage), as viser's client reads the messages in order."""
        shown: dict[str, bool] = {}
        for m in self.messages:
            name, kind = m.get("name"), m.get("type", "")
            if not isinstance(name, str) or kind.startswith("Gui"):
                continue
            if kind == "SetSceneNodeVisibilityMessage":
                if name in shown:
                    shown[name] = bool(m["visible"])
            elif kind == "RemoveSceneNodeMessage":
                shown = {n: v for n, v in shown.items() if n != name and not n.startswith(name + "/")}
            elif isinstance(m.get("props"), dict):  # a node added (or added again): drawn until hidden
                shown[name] = True

        def drawn(name: str) -> bool:
            parts = name.strip("/").split("/")
            return all(shown.get("/" + "/".join(parts[: i + 1]), True) for i in range(len(parts)))

        return {n for n, v in shown.items() if v and drawn(n)}

    async def send(self, type_name: str, **fields) -> None:
        await self.ws.send(msgspec.msgpack.encode({"type": type_name, **fields}))

    async def send_camera(self, position, look_at=(0.0, 0.0, 0.0), fov=0.9, size=(480, 640)) -> None:
        position = tuple(float(v) for v in position)
        await self.send_pose(wxyz_look_at(np.array(position), np.array(look_at)), position, look_at, fov, size)

    async def send_pose(self, wxyz, position, look_at, fov=0.9, size=(480, 640), up=(0.0, 0.0, 1.0)) -> None:
        """The browser's report of its camera (what it sends after every move, and after the server moved it)."""
        await self.send(
            "ViewerCameraMessage",
            wxyz=tuple(float(v) for v in wxyz),
            position=tuple(float(v) for v in position),
            fov=float(fov),
            near=0.01,
            far=100.0,
            image_height=int(size[0]),
            image_width=int(size[1]),
            look_at=tuple(float(v) for v in look_at),
            up_direction=tuple(float(v) for v in up),
        )

    async def click(self, label: str) -> None:
        await self.send("GuiUpdateMessage", uuid=self.gui[label]["uuid"], updates={"value": True})

    async def click_scene(self, origin, direction, screen_pos=(0.5, 0.5)) -> None:
        """A click in the 3D view: the world ray through the clicked pixel, as the browser sends it."""
        await self.send(
            "ScenePointerMessage",
            event_type="click",
            ray_origin=tuple(float(v) for v in origin),
            ray_direction=tuple(float(v) for v in direction),
            screen_pos=(tuple(screen_pos),),
            modifier=None,
        )

    async def set_value(self, label: str, value) -> None:
        await self.send("GuiUpdateMessage", uuid=self.gui[label]["uuid"], updates={"value": value})

    async def move_gizmo(self, name: str, position, wxyz=(1.0, 0.0, 0.0, 0.0)) -> None:
        position = tuple(float(v) for v in position)
        wxyz = tuple(float(v) for v in wxyz)
        await self.send("TransformControlsDragStartMessage", name=name, owner="")
        await self.send("TransformControlsUpdateMessage", name=name, wxyz=wxyz, position=position, owner="")
        await self.send("TransformControlsDragEndMessage", name=name, owner="")

    async def wait_for(self, pred: Callable[[dict], bool], timeout: float = 60.0, start: int = 0) -> dict:
        """The first message (from index `start`) satisfying `pred`; raises TimeoutError."""
        deadline = time.monotonic() + timeout
        i = start
        while True:
            while i < len(self.messages):
                if pred(self.messages[i]):
                    return self.messages[i]
                i += 1
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no matching viser message arrived")
            self._new.clear()
            try:
                await asyncio.wait_for(self._new.wait(), timeout=min(left, 0.5))
            except TimeoutError:
                pass

    async def wait_gui(self, label: str, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while label not in self.gui:
            if time.monotonic() > deadline:
                raise TimeoutError(f"GUI element {label!r} never arrived")
            await asyncio.sleep(0.05)
        return self.gui[label]
