"""The local API server process: ``python -m flows.api_server PARENT_PID IDLE_S PORT``.

Prefect's server app (``prefect.server.api.server:create_app``, the factory Prefect's own ephemeral server runs)
under uvicorn on 127.0.0.1:PORT, with the settings of the environment it inherits. With ``IDLE_S`` > 0 it stays up
for the next command until no request has come for that long (requests and open connections count), then shuts
down as on SIGTERM. With ``IDLE_S`` = 0 it belongs to the command that started it: on Linux it gets SIGTERM when
that command dies, however it dies (``PR_SET_PDEATHSIG``), and leaves at once if that happened already.
Exit status 3 (uvicorn's) when the port is taken.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Awaitable, Callable
from typing import Any

App = Callable[[dict, Callable[[], Awaitable[Any]], Callable[[Any], Awaitable[None]]], Awaitable[None]]


def die_with(parent: int) -> None:
    """SIGTERM to this process when ``parent`` dies (Linux); exit now if it is gone already."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the command stops the server at exit
        pass
    if os.getppid() != parent:
        sys.exit(0)


def idle_watched(app: App, idle_s: float) -> App:
    """The ASGI app, and a thread (from the end of the app's start-up on) that sends SIGTERM to this process once it
    has served nothing for ``idle_s``."""
    state = {"active": 0, "last": time.monotonic()}

    async def started(message: Any, send: Callable[[Any], Awaitable[None]]) -> None:
        """Pass a lifespan message on; the end of the start-up starts the idle clock."""
        if message.get("type") == "lifespan.startup.complete":
            state["last"] = time.monotonic()
            threading.Thread(target=watch, name="idle-watch", daemon=True).start()
        await send(message)

    async def watched(scope: dict, receive: Callable[[], Awaitable[Any]], send: Callable[[Any], Awaitable[None]]
                      ) -> None:
        """The app, with every request and connection counted while it lasts."""
        if scope["type"] == "lifespan":
            return await app(scope, receive, lambda message: started(message, send))
        if scope["type"] not in ("http", "websocket"):
            return await app(scope, receive, send)
        state["active"] += 1
        state["last"] = time.monotonic()
        try:
            await app(scope, receive, send)
        finally:
            state["active"] -= 1
            state["last"] = time.monotonic()

    def watch() -> None:
        """SIGTERM to this process once nothing has been served for ``idle_s``."""
        while True:
            time.sleep(min(idle_s, 2.0))
            if state["active"] == 0 and time.monotonic() - state["last"] > idle_s:
                os.kill(os.getpid(), signal.SIGTERM)
                return

    return watched


def main(argv: list[str]) -> None:
    """Run the server (arguments: parent pid, idle seconds, port)."""
    parent, idle_s, port = int(argv[0]), float(argv[1]), int(argv[2])
    if idle_s <= 0:
        die_with(parent)
    import uvicorn
    from prefect.server.api.server import create_app

    # ephemeral: the ephemeral server's services only (no scheduler, late runs, ...) and no UI; final: the last app
    # this process builds. create_app's documented arguments: what Prefect's own ephemeral server is given through
    # private settings
    app = create_app(ephemeral=True, final=True)
    uvicorn.run(idle_watched(app, idle_s) if idle_s > 0 else app, host="127.0.0.1", port=port, log_level="error",
                lifespan="on")


if __name__ == "__main__":
    main(sys.argv[1:])
