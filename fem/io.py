"""Atomic outputs: a failed or interrupted run never leaves a half-written file.

Each writer writes into a hidden temporary folder beside the target, then renames into place
(rank 0, after a barrier). XDMF and its HDF5 file are renamed together, so the reference from
the .xdmf to its .h5 stays valid.
"""

from __future__ import annotations

from mpi4py import MPI

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

#: Writes in progress, and a signal that arrived during one (see `interrupt_now`).
_writing = {"depth": 0, "pending": None}


def interrupt_now(signum) -> bool:
    """For a SIGINT/SIGTERM handler: True if the run may be interrupted now; False while a
    write is in progress, whose end then raises KeyboardInterrupt instead."""
    if _writing["depth"]:
        _writing["pending"] = signum
        return False
    return True


@contextlib.contextmanager
def _staged(target: Path, comm: MPI.Comm):
    """Yield a hidden temporary folder beside ``target``; on success its files are renamed
    into ``target``'s folder (rank 0, between barriers). The folder is removed however the
    block ends, and an interrupt (`interrupt_now`) waits for that: a write is finished and
    renamed, or leaves nothing."""
    _writing["depth"] += 1
    tmp = None
    try:
        if comm.rank == 0:
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = tempfile.mkdtemp(prefix=".partial-", dir=target.parent)
        tmp = Path(comm.bcast(tmp, root=0))
        yield tmp
        comm.Barrier()
        if comm.rank == 0:
            for f in sorted(tmp.iterdir()):
                os.replace(f, target.parent / f.name)
        comm.Barrier()
    finally:
        if comm.rank == 0 and tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        _writing["depth"] -= 1
        signum, _writing["pending"] = _writing["pending"], None
        if signum is not None and not _writing["depth"]:
            raise KeyboardInterrupt(f"signal {signum}")


def jsonable(x):
    """``json`` default: numpy arrays and scalars as lists and numbers."""
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x)}")


def write_on_root(path, write, comm: MPI.Comm) -> None:
    """Rank 0 calls ``write(tmp_path)``; the file, and any sidecar ``write`` puts beside it,
    are then renamed into ``path``'s folder together."""
    path = Path(path)
    with _staged(path, comm) as tmp:
        if comm.rank == 0:
            write(tmp / path.name)


def write_json(path, data: dict, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Write ``data`` as JSON to ``path`` atomically (rank 0 writes)."""
    def write(p):
        with open(p, "w") as fh:
            json.dump(data, fh, indent=2, default=jsonable)
            fh.write("\n")
    write_on_root(path, write, comm)


def write_npz(path, arrays: dict, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Write numpy arrays (the same on every rank) to ``path`` (.npz) atomically."""
    def write(p):
        with open(p, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    write_on_root(path, write, comm)


def write_grid(path, points, cells, point_data=None, cell_data=None,
               comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """One unstructured grid to ``path`` (.xdmf with its .h5, or .vtu), atomically, as ParaView's
    default reader for the suffix opens it (docs/decisions.md, "Files for ParaView").

    Args: (rank 0's; other ranks may pass None) points (N, 3) mm; cells: (cell type, (C, m)
    vertex indices), e.g. ``("tetra", tets)``; point_data / cell_data: ``{name: (N,) or (N, 3)}``
    / ``{name: (C,)}``.
    """
    def write(p):
        import meshio

        meshio.write(str(p), meshio.Mesh(
            np.asarray(points, float), [cells], point_data=dict(point_data or {}),
            cell_data={k: [np.asarray(v)] for k, v in (cell_data or {}).items()}))
    write_on_root(path, write, comm)


def write_text(path, text: str, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Write ``text`` (the same on every rank) to ``path`` atomically (rank 0 writes)."""
    def write(p):
        Path(p).write_text(text)
    write_on_root(path, write, comm)
