"""Start the explorer server and a headless Chromium on it: shared by the tests and
``bench.py explorer`` (no physics here)."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPLORE_WEB = [sys.executable, str(ROOT / "scripts" / "explore_web.py")]
#: Debian's Chromium and ChromeDriver (packages chromium, chromium-driver).
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
#: Headless, WebGL by SwiftShader on the CPU, and none of Chromium's own network traffic
#: (a closed network refuses it, many connections at a time).
CHROMIUM_ARGS = ("--headless=new", "--no-sandbox", "--use-gl=swiftshader",
                 "--enable-unsafe-swiftshader", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 "--disable-dev-shm-usage")


def mpirun(n: int, python: str | None = None) -> list:
    """The command prefix that runs a program on n ranks ([] for one) with the launcher of
    ``python``'s own MPI (default: this interpreter's): its venv's (PyPI's MPICH) where it
    has one, else the PATH's (Debian's Open MPI, run as root with --allow-run-as-root, and
    --oversubscribe beyond the cores)."""
    if n <= 1:
        return []
    exe = _launcher(python or sys.executable)
    extra = (["--allow-run-as-root", "--oversubscribe"]
             if os.geteuid() == 0 and _is_open_mpi(exe) else [])
    return [exe, *extra, "-n", str(n)]


def _launcher(python: str) -> str:
    own = Path(python).parent / "mpirun"
    return str(own) if own.exists() else shutil.which("mpirun") or shutil.which("mpiexec")


@functools.cache
def _is_open_mpi(exe: str) -> bool:
    out = subprocess.run([exe, "--version"], capture_output=True, text=True)
    return "Open MPI" in out.stdout + out.stderr


@contextlib.contextmanager
def explorer(args, mpirun=(), timeout: float = 600.0):
    """Run ``explore_web.py args`` (under ``mpirun`` if given, a command prefix) on a free
    loopback port; yield (base URL, process). On exit: SIGINT to rank 0 (every rank then
    exits 0; mpirun itself, signalled, reports 1), and the exit code is kept in
    ``process.returncode``."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([*mpirun, *EXPLORE_WEB, *args, "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            encoding="utf-8", errors="replace", env=env)
    try:
        url, pid, t0 = None, proc.pid, time.monotonic()
        for line in proc.stdout:
            m = re.search(r"(http://\S+/).*pid (\d+)", line)
            if m:
                url, pid = m.group(1), int(m.group(2))
                break
            if time.monotonic() - t0 > timeout:
                break
        if url is None:
            proc.kill()
            raise RuntimeError(f"the explorer did not start: {proc.stderr.read()[-3000:]}")
        yield url, proc
    finally:
        if proc.poll() is None:
            os.kill(pid, signal.SIGINT)
            try:
                proc.wait(timeout=120)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def request(url: str, body=None, raw: bytes | None = None, timeout: float = 600.0):
    """(status, decoded JSON or bytes) of a GET (``body`` None) or a POST of ``body`` as
    JSON (or ``raw`` bytes)."""
    data = raw if raw is not None else None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method="GET" if data is None else "POST",
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            status, payload, kind = r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as e:
        status, payload, kind = e.code, e.read(), e.headers.get("Content-Type", "")
    return status, json.loads(payload) if "json" in kind else payload


def chromium(width: int = 1400, height: int = 900):
    """A headless Chromium driven by Selenium through Debian's ChromeDriver, with the
    browser console kept (``driver.get_log("browser")``). Its temporary files go to a folder
    of its own, removed once the driver is gone: Chromium leaves a folder with its singleton
    socket in $TMPDIR on every ``quit()``."""
    import tempfile
    import weakref

    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in (*CHROMIUM_ARGS, f"--window-size={width},{height}"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    tmp = tempfile.mkdtemp(prefix="orthodiff-chromium-")
    try:
        driver = webdriver.Chrome(service=Service(CHROMEDRIVER, env={**os.environ,
                                                                     "TMPDIR": tmp}),
                                  options=opts)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    weakref.finalize(driver, shutil.rmtree, tmp, ignore_errors=True)
    return driver


def wait_ready(driver, timeout: float = 60.0) -> float:
    """Seconds until ``window.explorer.ready``; RuntimeError with the page's error after
    ``timeout``."""
    t0 = time.monotonic()
    while not driver.execute_script("return !!(window.explorer && window.explorer.ready)"):
        if time.monotonic() - t0 > timeout:
            err = driver.execute_script("return window.explorer && window.explorer.lastError")
            raise RuntimeError(f"the page was not ready after {timeout} s: {err}")
        time.sleep(0.02)
    return time.monotonic() - t0


def set_params(driver, values: dict) -> float:
    """Move sliders by ``window.explorer.setParams`` and wait for the frame: its
    ``lastFrameMs`` (event to drawn frame, ms)."""
    return driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "window.explorer.setParams(arguments[0]).then(() => done(window.explorer.lastFrameMs));",
        values)
