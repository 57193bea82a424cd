"""The ``crfedit ui`` web server (aiohttp): the page, its JSON API and a WebSocket for progress.

Security: every request and the WebSocket carry the session token (``?token=`` or the
``X-Crfedit-Token`` header; no cookie, which every port of 127.0.0.1 would share); the Host
header must name the address the server is bound to (no DNS rebinding) and an Origin header,
when sent, must be this server; bodies are limited to :data:`MAX_BODY`; files are written only
inside the work dir, under plain names; only safetensors files are read.

Concurrency: renders and selections run on one worker thread, edits on another, so the page
stays responsive while an edit runs.  One edit at a time: a second is refused with 409.  An
edit started by a page whose WebSocket closes (the tab was closed) is cancelled at its next
optimization step; nothing is written.  The two threads share the process's CPU threads
(:func:`compute_threads`), and :func:`open_page_session` loads the model on a thread that ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import html
import ipaddress
import itertools
import json
import secrets
import signal
import socket
import sys
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources

from aiohttp import WSMsgType, web

from ..errors import CrfError
from ..names import is_digits
from .recipe import parse_edit
from .session import UiSession

MAX_BODY = 2 * 1024 * 1024
"""Largest request body accepted (bytes)."""
TOKEN_HEADER = "X-Crfedit-Token"
LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
WILDCARD = ("0.0.0.0", "::", "")
SHUTDOWN_S = 3.0
"""Seconds open requests get to finish when the server stops (aiohttp waits 60 s by default)."""
STATIC_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html", ".svg": "image/svg+xml"}
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; "
       "frame-ancestors 'none'; base-uri 'none'; form-action 'none'")
PROGRESS_EVERY = 0.1
"""Seconds between progress messages of a running edit."""


COMPUTE_THREADS = 2
"""Threads of the server that run torch: the render pool's and the edit pool's."""


def compute_threads(requested: int) -> int:
    """torch's CPU threads for the server of a process given ``requested`` threads: a share for
    each of its :data:`COMPUTE_THREADS` (at least one).

    torch's OpenMP runtime (libgomp) keeps a team of worker threads for every thread that runs
    torch, and once all the teams hold more threads than the machine has cores, every team's
    idle workers sleep at once instead of spinning: each parallel region then waits for a wake-up.
    On 2 cores a loop of small matmuls ran 0.21 s on one thread and 0.35–0.40 s on either of two
    (as with ``OMP_WAIT_POLICY=passive``), and the page's colour edit took 0.57–0.88 s in the edit
    thread with 2 torch threads against 0.26–0.34 s with one (docs/benchmarks.md)."""
    return max(1, requested // COMPUTE_THREADS)


def open_page_session(model_path, data, edits, workdir, device: str, threads: int | None = None):
    """:func:`~crfedit.ui.session.open_session` for a server: sets torch's threads to
    :func:`compute_threads` of ``threads`` (default: torch's now) and loads on a thread that then
    ends, so that the calling thread keeps no OpenMP team beside the server's two."""
    import torch

    from ..runtime import configure_threads
    from .session import open_session

    configure_threads(compute_threads(torch.get_num_threads() if threads is None else threads))
    with ThreadPoolExecutor(1, thread_name_prefix="crfedit-load") as pool:
        return pool.submit(open_session, model_path, data, edits, workdir, device).result()


class Cancelled(Exception):
    """The page that started an edit went away (or pressed Cancel)."""


@dataclass
class Job:
    """One running (or finished) edit."""

    id: int
    kind: str
    client: str
    steps: int
    cancel: threading.Event = field(default_factory=threading.Event)
    step: int = 0
    state: str = "running"  # running | done | error | cancelled
    message: str = ""
    result: dict | None = None
    started: float = field(default_factory=time.perf_counter)


def _error(status: int, message: str) -> web.Response:
    return web.json_response({"error": " ".join(str(message).split())}, status=status)


def _unexpected(e: BaseException) -> str:
    return f"unexpected {e.__class__.__name__}: {' '.join(str(e).split()) or 'no message'} (see the terminal running crfedit ui)"


class Server:
    """The aiohttp application around one :class:`UiSession`."""

    def __init__(self, session: UiSession, token: str, bind_host: str):
        self.session, self.token, self.bind_host = session, token, bind_host
        self.port = 0
        self.render_pool = ThreadPoolExecutor(1, thread_name_prefix="crfedit-render")
        self.edit_pool = ThreadPoolExecutor(1, thread_name_prefix="crfedit-edit")
        self.sockets: dict[str, web.WebSocketResponse] = {}
        self.job: Job | None = None
        self._ids = itertools.count(1)
        self.loop: asyncio.AbstractEventLoop | None = None
        static = resources.files("crfedit.ui").joinpath("static")
        self.static = {p.name: p for p in static.iterdir() if p.is_file()}

    # ------------------------------------------------------------------------- the app

    def app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY, middlewares=[self.guard])
        r = app.router
        r.add_get("/", self.index)
        r.add_get("/static/{name}", self.static_file)
        r.add_get("/api/state", self.state)
        r.add_get("/api/view", self.view)
        r.add_get("/api/thumb", self.thumb)
        r.add_get("/api/angles", self.angles)
        r.add_get("/api/photo", self.photo)
        r.add_post("/api/select", self.select)
        r.add_post("/api/select/clear", self.clear_selection)
        r.add_post("/api/edit", self.edit)
        r.add_get("/api/job", self.job_status)
        r.add_post("/api/cancel", self.cancel)
        r.add_post("/api/stack/toggle", self.toggle)
        r.add_post("/api/stack/move", self.move)
        r.add_post("/api/stack/save", self.save)
        r.add_get("/api/stack/download", self.download)
        r.add_post("/api/bake", self.bake)
        r.add_get("/api/shell", self.shell)
        r.add_get("/api/ws", self.websocket)
        app.on_shutdown.append(self._close_sockets)
        return app

    def _host_ok(self, host: str) -> bool:
        """Whether a request's Host header names this server (against DNS rebinding): a loopback
        name or the bound address, at this port; on a wildcard bind (0.0.0.0, ::) any IP address
        or this machine's own host name, but no other name, since a rebinding attack needs one."""
        if self.bind_host not in WILDCARD:
            names = {*LOOPBACK, self.bind_host if ":" not in self.bind_host else f"[{self.bind_host}]"}
            return host.lower() in {f"{n}:{self.port}".lower() for n in names}  # host names ignore case
        name, sep, port = host.rpartition(":")
        if not sep or port != str(self.port):
            return False
        try:
            ipaddress.ip_address(name[1:-1] if name.startswith("[") and name.endswith("]") else name)
            return True
        except ValueError:
            return name.lower() in {*LOOPBACK, socket.gethostname().lower(), socket.getfqdn().lower()}

    @web.middleware
    async def guard(self, request: web.Request, handler):
        """Host, token and Origin checks, body size, and one-line JSON errors."""
        host = request.headers.get("Host", "")
        if not self._host_ok(host):
            return _error(403, f"refused: Host {host[:60]!r} is not this server (open the URL crfedit ui printed)")
        given = request.query.get("token") or request.headers.get(TOKEN_HEADER, "")
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            return _error(403, "refused: missing or wrong session token (open the URL crfedit ui printed, with its ?token=)")
        origin = request.headers.get("Origin")
        if origin is not None and origin != f"http://{host}":
            return _error(403, f"refused: requests from {origin[:60]!r} may not drive this page")
        if (request.content_length or 0) > MAX_BODY:
            return _error(413, f"the request is larger than {MAX_BODY >> 20} MB")
        try:
            response = await handler(request)
        except CrfError as e:
            return _error(400, str(e))
        except web.HTTPRequestEntityTooLarge:
            return _error(413, f"the request is larger than {MAX_BODY >> 20} MB")
        except web.HTTPException as e:
            if e.status < 400 or e.content_type == "application/json":  # a redirect, or a refusal of ours already
                raise
            response = _error(e.status, e.reason)  # a wrong method or path: the same one-line JSON as every refusal
            if "Allow" in e.headers:  # a 405 says which methods the path takes (HTTP requires it)
                response.headers["Allow"] = e.headers["Allow"]
            return response
        except Exception as e:  # one line for the page; the traceback for the terminal
            traceback.print_exc(file=sys.stderr)
            return _error(500, _unexpected(e))
        response.headers.setdefault("Cache-Control", "no-store")
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("Referrer-Policy", "no-referrer")
        return response

    async def _run(self, fn, *args, pool=None):
        return await asyncio.get_running_loop().run_in_executor(pool or self.render_pool, fn, *args)

    @staticmethod
    async def _json(request: web.Request):
        try:
            body = await request.json()
        except web.HTTPRequestEntityTooLarge:
            raise
        except ValueError:
            raise CrfError("the request body is not valid JSON") from None
        except RecursionError:
            raise CrfError("the request body nests its JSON too deeply") from None
        if not isinstance(body, dict):
            raise CrfError("expected a JSON object")
        return body

    def _busy(self) -> None:
        if self.job is not None and self.job.state == "running":
            message = f"an edit ({self.job.kind}) is already running: wait for it, or press Cancel in the tab that started it"
            raise web.HTTPConflict(text=json.dumps({"error": message}), content_type="application/json")

    # ------------------------------------------------------------------------- page and images

    async def index(self, request):
        text = self.static["index.html"].read_text(encoding="utf-8").replace("{{token}}", html.escape(self.token))
        return web.Response(text=text, content_type="text/html", headers={"Content-Security-Policy": CSP})

    async def static_file(self, request):
        name = request.match_info["name"]
        path = self.static.get(name)
        kind = STATIC_TYPES.get(name[name.rfind("."):]) if "." in name else None
        if path is None or kind is None:
            return _error(404, f"no such file: {name[:60]}")
        return web.Response(body=path.read_bytes(), content_type=kind, headers={"Cache-Control": "no-cache"})

    async def state(self, request):
        info = await self._run(self.session.info)
        info["busy"] = self.job is not None and self.job.state == "running"
        return web.json_response(info)

    @staticmethod
    def _view_query(q) -> object:
        if "view" in q:
            return q["view"]
        try:
            return {"azimuth": float(q.get("az", "")), "elevation": float(q.get("el", ""))}
        except ValueError:
            raise CrfError("view: give view=SPLIT:INDEX or az=DEGREES&el=DEGREES") from None

    @staticmethod
    def _png(data: bytes) -> web.Response:
        return web.Response(body=data, content_type="image/png")

    async def view(self, request):
        q = request.query
        which = q.get("state", "current")
        png = await self._run(self.session.render, q.get("instance", ""), self._view_query(q), which, q.get("tint") == "1")
        return self._png(png)

    async def thumb(self, request):
        return self._png(await self._run(self.session.thumbnail, request.query.get("instance", "")))

    async def angles(self, request):
        return web.json_response(await self._run(self.session.view_angles, request.query.get("instance", "")))

    async def photo(self, request):
        q = request.query
        index = q.get("index", "")
        if not is_digits(index):
            raise CrfError("index: expected a view number")
        return self._png(await self._run(self.session.photo, q.get("instance", ""), q.get("split", ""), int(index)))

    # ------------------------------------------------------------------------- selection

    async def select(self, request):
        body = await self._json(request)
        return web.json_response(await self._run(self.session.select, body))

    async def clear_selection(self, request):
        body = await self._json(request)
        await self._run(self.session.clear_selection, body.get("instance"))
        return web.json_response({"ok": True})

    # ------------------------------------------------------------------------- edits

    async def edit(self, request):
        """Start an edit; 202 with the job id.  Progress, the result or the error go to the
        WebSockets (and to GET /api/job)."""
        self._busy()
        body = await self._json(request)
        req = await self._run(parse_edit, body, self.session.model)
        self._busy()
        job = Job(next(self._ids), req.kind, str(body.get("client", ""))[:64], req.options.steps)
        self.job = job
        loop = asyncio.get_running_loop()
        last = [0.0]

        def on_step(step: int, loss: float) -> None:
            if job.cancel.is_set():
                raise Cancelled()
            job.step = step
            now = time.perf_counter()
            if now - last[0] >= PROGRESS_EVERY or step == job.steps:
                last[0] = now
                loop.call_soon_threadsafe(self._broadcast, {"type": "progress", "job": job.id, "kind": job.kind, "step": step, "steps": job.steps})

        future = loop.run_in_executor(self.edit_pool, self.session.run_edit, req, on_step)
        future.add_done_callback(lambda f: self._finished(job, f))
        return web.json_response({"job": job.id, "steps": job.steps}, status=202)

    def _finished(self, job: Job, future) -> None:
        error = future.exception()
        if error is None:
            job.state, job.result = "done", future.result()
            message = {"type": "done", "job": job.id, **job.result}
        elif isinstance(error, Cancelled):
            job.state, job.message = "cancelled", "the edit was cancelled; the stack is as it was"
            message = {"type": "cancelled", "job": job.id, "message": job.message}
        else:
            if not isinstance(error, CrfError):
                traceback.print_exception(error, file=sys.stderr)
            job.state = "error"
            job.message = str(error) if isinstance(error, CrfError) else _unexpected(error)
            message = {"type": "error", "job": job.id, "message": job.message}
        message["seconds"] = round(time.perf_counter() - job.started, 3)
        self._broadcast(message)

    def _broadcast(self, message: dict) -> None:
        for ws in list(self.sockets.values()):
            if not ws.closed:
                asyncio.ensure_future(ws.send_json(message))

    async def job_status(self, request):
        job = self.job
        if job is None:
            return web.json_response({"state": "none"})
        out = {"job": job.id, "kind": job.kind, "state": job.state, "step": job.step, "steps": job.steps, "message": job.message}
        if job.result is not None:
            out["result"] = job.result
        return web.json_response(out)

    async def cancel(self, request):
        if self.job is None or self.job.state != "running":
            raise CrfError("no edit is running")
        self.job.cancel.set()
        return web.json_response({"job": self.job.id, "cancelling": True})

    # ------------------------------------------------------------------------- stack

    async def toggle(self, request):
        self._busy()
        body = await self._json(request)
        return self._stack_changed(await self._run(self.session.toggle, body.get("id"), body.get("enabled")))

    async def move(self, request):
        self._busy()
        body = await self._json(request)
        return self._stack_changed(await self._run(self.session.move, body.get("id"), body.get("to")))

    def _stack_changed(self, result: dict):
        """The reply to a stack change, which every open page also hears (``type: stack``): a
        second tab's stack and state follow it instead of going stale."""
        self._broadcast({"type": "stack", "stack": result["stack"], "state": result["state"]})
        return web.json_response(result)

    async def save(self, request):
        body = await self._json(request)
        path, written = await self._run(self.session.save, body.get("id"), body.get("name"))
        return web.json_response({"path": str(path), "again": not written})

    async def download(self, request):
        raw = request.query.get("id", "")
        if not is_digits(raw):
            raise CrfError("id: expected an edit number")
        name, data = await self._run(self.session.delta_file, int(raw))
        return web.Response(body=data, content_type="application/octet-stream",
                            headers={"Content-Disposition": f'attachment; filename="{name}"'})

    async def bake(self, request):
        self._busy()
        body = await self._json(request)
        return web.json_response(await self._run(self.session.bake, body.get("name")))

    async def shell(self, request):
        return web.Response(text=await self._run(self.session.shell), content_type="text/plain")

    # ------------------------------------------------------------------------- websocket

    async def websocket(self, request):
        client = request.query.get("client", "")[:64] or secrets.token_hex(8)
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=64 * 1024)
        await ws.prepare(request)
        self.sockets[client] = ws
        try:
            await ws.send_json({"type": "hello", "client": client})
            async for msg in ws:
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.sockets.pop(client, None)
            job = self.job
            if job is not None and job.state == "running" and job.client == client:
                job.cancel.set()  # the tab that started it is gone
        return ws

    async def _close_sockets(self, app) -> None:
        if self.job is not None:
            self.job.cancel.set()
        for ws in list(self.sockets.values()):
            await ws.close()

    def shutdown_pools(self) -> None:
        """Stop the worker pools; after the runner's cleanup, which lets requests in flight
        finish (shut first, a render the page asked for in the last moment failed as an
        unexpected RuntimeError instead of the page losing the server)."""
        if self.job is not None:
            self.job.cancel.set()
        self.render_pool.shutdown(wait=False, cancel_futures=True)
        self.edit_pool.shutdown(wait=False, cancel_futures=True)


# ----------------------------------------------------------------------------- running


def _listen_fix(error: OSError, host: str) -> str:
    """What to change when the page cannot listen: the port when it is taken (or not ours to
    take), else the host (a name that does not resolve, an address this machine does not have)."""
    import errno
    import socket

    if error.errno in (errno.EADDRINUSE, errno.EACCES):
        return "pick another --port (--port 0 takes a free one)"
    if isinstance(error, socket.gaierror) or error.errno == errno.EADDRNOTAVAIL:
        return f"--host {host} is not an address of this machine (127.0.0.1 for this machine alone, 0.0.0.0 for every interface)"
    return "check --host and --port"


async def _start(server: Server, host: str, port: int) -> web.AppRunner:
    runner = web.AppRunner(server.app(), access_log=None, shutdown_timeout=SHUTDOWN_S)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    try:
        await site.start()
    except OSError as e:
        await runner.cleanup()
        raise CrfError(f"cannot listen on {host}:{port} ({e.strerror or e}); {_listen_fix(e, host)}") from None
    server.port = site._server.sockets[0].getsockname()[1]
    return runner


def url_of(server: Server, host: str) -> str:
    shown = "127.0.0.1" if host in WILDCARD else (f"[{host}]" if ":" in host else host)
    return f"http://{shown}:{server.port}/?token={server.token}"


def serve(session: UiSession, host: str, port: int, on_ready) -> None:
    """Serve until Ctrl-C (SIGINT) or SIGTERM; ``on_ready(url)`` once listening.

    The stop signals are the event loop's own handlers where the platform has them
    (``loop.add_signal_handler``): the loop's self-pipe is then the process's signal wake-up
    fd, so the loop wakes whichever thread the kernel hands the signal to.  asyncio.run's
    default SIGINT handling runs only once the main thread leaves its ``epoll_wait``, which a
    signal delivered to an idle worker thread of the render or edit pool never makes it do:
    the server then did not stop (seen once in CI)."""
    server = Server(session, secrets.token_urlsafe(24), host)

    async def main():
        stop, loop, handled = asyncio.Event(), asyncio.get_running_loop(), []
        runner = await _start(server, host, port)
        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                # Windows has no loop signal handlers (a RuntimeError subclass); off the main
                # thread they raise too: Ctrl-C then stays asyncio.run's KeyboardInterrupt.
                with contextlib.suppress(RuntimeError, ValueError):
                    loop.add_signal_handler(sig, stop.set)
                    handled.append(sig)
            on_ready(url_of(server, host))
            await stop.wait()
        finally:
            for sig in handled:
                loop.remove_signal_handler(sig)
            await runner.cleanup()  # stops listening, closes the sockets, lets requests finish
            server.shutdown_pools()

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass


@dataclass
class Running:
    """A server running on a thread of its own (:func:`run_in_thread`)."""

    url: str
    token: str
    port: int
    stop: object  # () -> None
    server: Server


def run_in_thread(session: UiSession, host: str = "127.0.0.1", port: int = 0) -> Running:
    """Start the server on its own event loop thread (a notebook, a test, a benchmark); the
    returned handle's ``stop()`` shuts it down."""
    server = Server(session, secrets.token_urlsafe(24), host)
    loop = asyncio.new_event_loop()
    ready, failure, holder = threading.Event(), [], {}

    def run():
        asyncio.set_event_loop(loop)
        try:
            holder["runner"] = loop.run_until_complete(_start(server, host, port))
        except BaseException as e:  # reported to the caller
            failure.append(e)
            ready.set()
            return
        ready.set()
        loop.run_forever()
        loop.run_until_complete(holder["runner"].cleanup())
        server.shutdown_pools()
        loop.close()

    thread = threading.Thread(target=run, name="crfedit-ui", daemon=True)
    thread.start()
    ready.wait()
    if failure:
        raise failure[0]

    def stop():
        if loop.is_running():
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=10)

    return Running(url_of(server, host), server.token, server.port, stop, server)
