"""gmsh, imported without its import's side effect: Debian's gmsh 4.8 sets SIGINT to SIG_DFL
when imported (until `gmsh.finalize`), so that Ctrl-C killed a script instead of unwinding
it (`scripts._common.run_main`: exit 130, nothing half-written)."""

import signal
import threading


def import_gmsh():
    """The gmsh module; SIGINT's handler as it was."""
    was = signal.getsignal(signal.SIGINT)
    import gmsh as module

    if was is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, was)
    return module
