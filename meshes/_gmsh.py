"""gmsh sessions that leave SIGINT and SIGTERM to the scripts (`scripts._common.run_main`:
exit 130, nothing half-written). Debian's gmsh 4.8 sets SIGINT to SIG_DFL when imported;
PyPI's 4.15 sets both to SIG_DFL in `gmsh.initialize` and leaves them there: Ctrl-C or a
kill during a run that meshed then killed the script instead of unwinding it."""

import contextlib
import signal
import threading

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def gmsh_session(args=()):
    """gmsh, initialised with ``args`` for the block and finalised after it; the handlers of
    `_SIGNALS` as they were, during the block and after it."""
    was = {s: signal.getsignal(s) for s in _SIGNALS}

    def restore():
        if threading.current_thread() is threading.main_thread():
            for s, handler in was.items():
                if handler is not None:
                    signal.signal(s, handler)

    import gmsh

    try:
        gmsh.initialize(list(args))
        restore()
        yield gmsh
    finally:
        gmsh.finalize()
        restore()
