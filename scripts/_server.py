"""The explorer's HTTP server: FastAPI on uvicorn in a thread of rank 0, every computation on
the main threads of all ranks (``scripts/explore_web.py``).

Rank 0's HTTP thread validates a request (`Session.request_params`, `request_targets`: local
checks), queues it and waits; rank 0's main thread broadcasts it and every rank runs the same
`inverse.session.Session` method, so MPI, PETSc and dolfinx are only ever called from the
main threads. One computation at a time: a request that finds one running gets 503 at once.
Ranks other than 0 wait for the next broadcast by polling (5 ms sleeps), so an idle explorer
leaves the cores to the browser.
"""


import concurrent.futures
import json
import logging
import os
import pickle
import queue
import signal
import socket
import threading
import time

import numpy as np

from meshes.errors import InputError, OrthodiffError

log = logging.getLogger("orthodiff.explore_web")

#: Requests that move p0 (the page then reloads the scene and the sensitivities).
MOVES_P0 = ("relinearise", "plan", "match")
#: What POST /api/plan takes: targets, occlusion, and plan.py's options.
PLAN_KEYS = ("targets", "occlusion", "tikhonov", "ftol", "max_iterations")
#: Poll interval of the waiting ranks, s.
POLL_S = 0.005


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on host:port (0: any free port); `InputError` in one line."""
    try:
        info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(info[0], socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(info[4])
        sock.listen(64)
    except OSError as e:
        raise InputError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    return sock


def _reject_constant(text):
    raise InputError(f"{text} is not a number (JSON allows finite numbers only)")


def parse_body(body: bytes, max_body: int) -> dict:
    """A request's JSON object; `InputError` for anything else (NaN and Infinity too)."""
    if len(body) > max_body:
        raise InputError(f"request body larger than {max_body} bytes")
    try:
        data = json.loads(body or b"{}", parse_constant=_reject_constant)
    except InputError:
        raise
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"malformed JSON: {e}") from None
    if not isinstance(data, dict):
        raise InputError("the request body must be a JSON object")
    return data


class Server:
    """Serve ``session`` until SIGINT or SIGTERM; `run` returns 0. Collective.

    Args:
        session: the `inverse.session.Session` (on every rank).
        sock: rank 0's listening socket (`bind`), None elsewhere.
        page: {url path: file name in ``web``}; three: three.js's npm folder.
    """

    def __init__(self, session, comm, sock, page: dict, web, three, max_body: int):
        self.session, self.comm, self.sock = session, comm, sock
        self.page, self.web, self.three, self.max_body = page, web, three, max_body
        self.stop = threading.Event()
        self.busy = threading.Lock()
        self.jobs: queue.Queue = queue.Queue()
        self.progress = {"running": None, "history": []}
        self._refresh()

    # ------------------------------------------------------------------ all ranks
    def run(self) -> int:
        def stop(signum, frame):
            self.stop.set()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, stop)
        if self.comm.rank != 0:
            while True:
                job = self._receive()
                if job is None:
                    return 0
                self._execute(*job)
        import uvicorn

        server = uvicorn.Server(uvicorn.Config(self.app(), log_level="warning",
                                               access_log=False, lifespan="off"))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [self.sock]},
                                  daemon=True)
        thread.start()
        host, port = self.sock.getsockname()[:2]
        print(f"orthodiff explorer: http://{host}:{port}/  ({self.comm.size} rank(s), rank 0 "
              f"pid {os.getpid()}; Ctrl-C or SIGTERM stops it)", flush=True)
        try:
            while not self.stop.is_set():
                try:
                    name, kwargs, future = self.jobs.get(timeout=0.1)
                except queue.Empty:
                    continue
                self._send((name, kwargs))
                future.set_result(self._execute(name, kwargs))
        finally:
            server.should_exit = True
            self._send(None)
            while not self.jobs.empty():
                self.jobs.get()[2].set_result(("busy", "the explorer is stopping"))
            thread.join(timeout=5)
        log.info("explorer stopped")
        return 0

    def _execute(self, name: str, kwargs: dict):
        """Run one session method on every rank: ("ok", result) or (kind, message)."""
        if name == "plan":
            self.progress = {"running": "plan", "history": []}
            kwargs = dict(kwargs, progress=self._progress)
        try:
            out = getattr(self.session, name)(**kwargs)
            if name in MOVES_P0:
                self._refresh()
            return "ok", out
        except InputError as e:
            return "bad", str(e)
        except OrthodiffError as e:   # a solver failure: the message, no traceback
            return "failed", str(e)
        except Exception:
            log.exception("request %s failed", name)
            return "error", "internal error (see the server's log)"
        finally:
            self.progress = dict(self.progress, running=None)

    def _progress(self, entry: dict):
        self.progress = {"running": "plan",
                         "history": self.progress["history"] + [json.loads(_dumps(entry))]}

    def _refresh(self):
        """The cached answers of GET /api/scene and /api/sensitivity (collective)."""
        scene = _dumps(self.session.payload()).encode()
        self.cache = {"scene": scene, "sensitivity": self.session.sensitivity_bytes()}

    # ------------------------------------------------------------------ broadcast
    def _send(self, job):
        if self.comm.size == 1:
            return
        data = pickle.dumps(job)   # the header by Ibcast: it matches the waiting ranks' Ibcast
        self.comm.Ibcast(np.array([len(data)], dtype=np.int64), root=0).Wait()
        self.comm.Bcast(bytearray(data), root=0)

    def _receive(self):
        n = np.zeros(1, dtype=np.int64)
        req = self.comm.Ibcast(n, root=0)
        while not req.Test():
            time.sleep(POLL_S)
        buf = bytearray(int(n[0]))
        self.comm.Bcast(buf, root=0)
        return pickle.loads(buf)

    # ------------------------------------------------------------------ HTTP (rank 0)
    def submit(self, name: str, arguments):
        """Validate with ``arguments()`` (the session's local checks: its kwargs, or
        `InputError`), queue ``name`` for the main thread and wait: (status, JSON-able
        body). Validation runs under the computation lock, so it sees the scene the
        computation will use (a plan may change the parameters)."""
        if not self.busy.acquire(blocking=False):
            return 503, {"error": "busy: another computation is running; try again when "
                                  "it has finished"}
        try:
            if self.stop.is_set():
                return 503, {"error": "the explorer is stopping"}
            try:
                kwargs = arguments()
            except InputError as e:
                return 400, {"error": str(e)}
            future = concurrent.futures.Future()
            self.jobs.put((name, kwargs, future))
            kind, out = future.result()
        finally:
            self.busy.release()
        status = {"ok": 200, "bad": 400, "failed": 422, "busy": 503, "error": 500}[kind]
        return status, out if kind == "ok" else {"error": out}

    def app(self):
        """The FastAPI application: the page, three.js and the JSON API."""
        from fastapi import FastAPI, Request
        from fastapi.responses import FileResponse, Response
        from fastapi.staticfiles import StaticFiles
        from starlette.concurrency import run_in_threadpool
        from starlette.exceptions import HTTPException

        app = FastAPI(title="orthodiff explorer", docs_url=None, redoc_url=None,
                      openapi_url=None)
        session = self.session

        def reply(status, body):
            return Response(_dumps(body), status_code=status, media_type="application/json")

        @app.exception_handler(HTTPException)
        async def http_error(request, exc):
            return reply(exc.status_code, {"error": str(exc.detail)})

        @app.exception_handler(Exception)
        async def any_error(request, exc):   # no traceback reaches the client
            log.exception("request failed")
            return reply(500, {"error": "internal error (see the server's log)"})

        for path, name in self.page.items():
            def page(name=name):
                return FileResponse(self.web / name, headers={"Cache-Control": "no-cache"})
            app.get(path, include_in_schema=False)(page)
        for sub in ("build", "examples/jsm"):
            app.mount(f"/vendor/three/{sub}", StaticFiles(directory=self.three / sub))

        @app.get("/api/scene")
        def scene():
            return Response(self.cache["scene"], media_type="application/json")

        @app.get("/api/sensitivity")
        def sensitivity():
            return Response(self.cache["sensitivity"], media_type="application/octet-stream")

        @app.get("/api/progress")
        def progress():
            return self.progress

        async def body(request: Request, keys):
            data = parse_body(await request.body(), self.max_body)
            unknown = [k for k in data if k not in keys]
            if unknown:
                raise InputError(f"unknown key(s) {unknown}; this request takes {list(keys)}")
            return data

        def with_params(name):
            async def endpoint(request: Request):
                try:
                    data = await body(request, ("p",))
                except InputError as e:
                    return reply(400, {"error": str(e)})
                return reply(*await run_in_threadpool(self.submit, name, lambda: {
                    "p": session.request_params(data.get("p", {}))}))
            return endpoint

        for name in ("solve", "corrected", "relinearise", "match", "export"):
            app.post(f"/api/{name}")(with_params(name))

        def plan_arguments(data):   # Session.plan checks the occlusion and the options
            return dict(data, targets=session.request_targets(data.get("targets")),
                        occlusion=data.get("occlusion", session.occlusion))

        @app.post("/api/plan")
        async def plan(request: Request):
            try:
                data = await body(request, PLAN_KEYS)
            except InputError as e:
                return reply(400, {"error": str(e)})
            return reply(*await run_in_threadpool(self.submit, "plan",
                                                  lambda: plan_arguments(data)))

        return app


def _dumps(body) -> str:
    """JSON text with numpy values; a NaN never leaves: it raises (a 500), not 'NaN'."""
    from fem.io import jsonable

    return json.dumps(body, default=jsonable, allow_nan=False)
