"""The interactive tool in the browser (``dyknow ui``): the computation graph of every manager
reachable, live, beside the DyKnow paper's control panel (active units, library, create,
connect, requests, unit details).

The page is static (``static/``: plain HTML, CSS and JavaScript, with cytoscape.js vendored: no
internet and no build step); :mod:`dyknow.ui.server` pushes the model to it and forwards its
actions to the managers' services.
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable
from typing import Any

from dyknow.client import Client
from dyknow.ui.server import ModelWatch, check_bind, make_app, serve

__all__ = ["run_ui"]


def run_ui(
    client: Client,
    *,
    host: str = "127.0.0.1",
    port: int = 8321,
    token: str | None = None,
    ready: Callable[[str], None] = print,
    recorded: dict[str, Any] | None = None,
) -> int:
    """Serve the tool until SIGINT or SIGTERM; ``ready(url)`` is told the URL to open. Returns 0.
    ``recorded``: a verdict timeline of requirements checked over a recording
    (:func:`~dyknow.ui.server.recorded_timeline`), shown beside the live one."""
    token = check_bind(host, token)

    async def main() -> None:
        with ModelWatch(client, recorded=recorded) as watch:
            runner, server = await serve(make_app(client, watch, token=token, bind=host), host, port)
            bound = server.sockets[0].getsockname()[1] if server.sockets else port
            shown = f"[{host}]" if ":" in host else host
            ready(f"http://{shown}:{bound}/" + (f"?token={token}" if token else ""))
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, stop.set)
            await stop.wait()
            server.close()
            await runner.cleanup()

    asyncio.run(main())
    return 0
