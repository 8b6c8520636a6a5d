"""The dashboard's web server (aiohttp): one page, plotly.js, a snapshot and a WebSocket of updates.

Safety rules (tested in tests/test_dashboard.py):

* it listens on 127.0.0.1 unless ``host`` names another interface, and then
  only with a token (:func:`check_bind`); with a token every request must
  carry it (``?token=``, ``Authorization: Bearer``, or the cookie the page
  sets), compared in constant time;
* on a loopback address the ``Host`` header must name a loopback host (a web
  page elsewhere cannot reach it through DNS rebinding), and a WebSocket's
  ``Origin``, when sent, must be this server;
* GET only: nothing a page sends changes anything on disk or in the room;
* the files are read once per change by one timer (:meth:`Hub.poll`), the
  same update string goes to every page through a bounded queue each; a page
  that does not keep up is disconnected (it reconnects and gets a snapshot)
  rather than slowing the others, and the positioning, another process
  writing the files, never waits for a page.
"""
from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
from pathlib import Path

from psdcal.errors import InputError

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1", "[::1]")
#: Updates queued for one page before it is dropped as too slow.
QUEUE = 256
MIN_TOKEN = 16


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``."""
    h = host.strip("[]")
    if h == "localhost":
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str | None, allow_remote: bool) -> None:
    """Refuse a non-loopback ``host`` without ``--allow-remote`` and a token; refuse a short token.

    Raises
    ------
    InputError
        One line, naming the option.
    """
    if token is not None and len(token) < MIN_TOKEN:
        raise InputError(f"the token must have at least {MIN_TOKEN} characters (e.g. `python -c \"import secrets; "
                         "print(secrets.token_urlsafe())\"`)", field="token")
    if is_loopback(host):
        return
    if not allow_remote:
        raise InputError(f"--host {host} serves the room to other machines: add --allow-remote and --token "
                         "to do that on purpose", field="host")
    if not token:
        raise InputError(f"--host {host} with --allow-remote needs --token (every request must carry it)",
                         field="token")


def _token_ok(request, token: str | None) -> bool:
    if not token:
        return True
    given = request.query.get("token") or request.cookies.get("psdcal_token") or ""
    auth = request.headers.get("Authorization", "")
    if auth.startswith("Bearer "):
        given = given or auth[7:]
    return hmac.compare_digest(given.encode(), token.encode())


def _host_ok(request, host: str) -> bool:
    if not is_loopback(host):
        return True  # the token protects a served interface
    name = request.host.rsplit(":", 1)[0] if not request.host.endswith("]") else request.host
    return is_loopback(name)


def make_app(hub, *, host: str = "127.0.0.1", token: str | None = None, poll_s: float = 0.02):
    """The aiohttp application serving ``hub`` (see the module docstring)."""
    from aiohttp import WSMsgType, web

    from psdcal.report.dashboard.page import plotly_js, render

    clients: set = set()
    state = {"snapshot": None}

    @web.middleware
    async def guard(request, handler):
        if not _host_ok(request, host):
            raise web.HTTPForbidden(text="host not allowed")
        if not _token_ok(request, token):
            raise web.HTTPForbidden(text="token required")
        resp = await handler(request)
        if token and request.query.get("token") and isinstance(resp, web.Response):
            resp.set_cookie("psdcal_token", token, httponly=True, samesite="Strict")
        resp.headers.setdefault("Cache-Control", "no-store")
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        return resp

    def snapshot_text() -> str:
        if state["snapshot"] is None:
            state["snapshot"] = json.dumps(hub.snapshot(), allow_nan=False, separators=(",", ":"))
        return state["snapshot"]

    async def index(request):
        return web.Response(text=render(live=True, title=hub.opts.title), content_type="text/html")

    async def plotly(request):
        return web.Response(body=plotly_js().encode("utf-8"), content_type="application/javascript",
                            headers={"Cache-Control": "max-age=3600"})

    async def snapshot(request):
        return web.Response(text=snapshot_text(), content_type="application/json")

    async def ws_handler(request):
        origin = request.headers.get("Origin")
        if origin and origin.split("://", 1)[-1] != request.host:
            raise web.HTTPForbidden(text="origin not allowed")
        ws = web.WebSocketResponse(heartbeat=20)
        await ws.prepare(request)
        queue: asyncio.Queue = asyncio.Queue(QUEUE)
        await ws.send_str(snapshot_text())
        clients.add(queue)

        async def sender():
            while True:
                msg = await queue.get()
                if msg is None:
                    await ws.close()
                    return
                await ws.send_str(msg)

        task = asyncio.ensure_future(sender())
        try:
            async for m in ws:  # the page sends nothing that changes anything; read to notice the close
                if m.type == WSMsgType.ERROR:
                    break
        finally:
            clients.discard(queue)
            task.cancel()
        return ws

    async def poller(app):
        async def loop():
            while True:
                msg = hub.poll()
                if msg is not None:
                    state["snapshot"] = None
                    text = json.dumps(msg, allow_nan=False, separators=(",", ":"))
                    for q in list(clients):
                        try:
                            q.put_nowait(text)
                        except asyncio.QueueFull:  # too slow: drop it (its page reconnects, gets a snapshot)
                            clients.discard(q)
                            while not q.empty():  # make room for the close marker
                                q.get_nowait()
                            q.put_nowait(None)
                await asyncio.sleep(poll_s)

        task = asyncio.ensure_future(loop())
        yield
        task.cancel()

    app = web.Application(middlewares=[guard])
    app.router.add_get("/", index)
    app.router.add_get("/plotly.min.js", plotly)
    app.router.add_get("/snapshot.json", snapshot)
    app.router.add_get("/ws", ws_handler)
    app.cleanup_ctx.append(poller)
    app["clients"] = clients
    return app


def serve(hub, *, host: str, port: int, token: str | None, poll_s: float, ready=None) -> None:
    """Run the server until interrupted; ``ready(url)`` is called once it listens."""
    from aiohttp import web

    async def main():
        app = make_app(hub, host=host, token=token, poll_s=poll_s)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, host, port)
        await site.start()
        actual = runner.addresses[0][1] if runner.addresses else port
        shown = f"[{host}]" if ":" in host else host
        if ready is not None:
            ready(f"http://{shown}:{actual}/" + (f"?token={token}" if token else ""))
        try:
            await asyncio.Event().wait()
        finally:
            await runner.cleanup()

    asyncio.run(main())


def export_html(hub, out_path) -> None:
    """Write the static page of everything ``hub`` holds (one self-contained HTML file)."""
    from psdcal._atomic import atomic_path
    from psdcal.report.dashboard.page import render

    text = render(live=False, title=hub.opts.title, data=hub.drain())
    with atomic_path(out_path, suffix=Path(out_path).suffix or ".html") as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
