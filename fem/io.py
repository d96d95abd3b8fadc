"""Atomic outputs: a failed or interrupted run never leaves a half-written file.

Each writer writes into a hidden temporary folder beside the target, then renames into place
(rank 0, after a barrier). XDMF and its HDF5 file are renamed together, so the reference from
the .xdmf to its .h5 stays valid.
"""

from __future__ import annotations

from mpi4py import MPI

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np


def _tmpdir(target: Path, comm: MPI.Comm) -> Path:
    target.parent.mkdir(parents=True, exist_ok=True) if comm.rank == 0 else None
    name = tempfile.mkdtemp(prefix=".partial-", dir=target.parent) if comm.rank == 0 else None
    return Path(comm.bcast(name, root=0))


def _discard(tmp: Path, comm: MPI.Comm):
    """Remove a temporary folder after a failed or interrupted write (local, no barrier)."""
    if comm.rank == 0:
        shutil.rmtree(tmp, ignore_errors=True)


def _commit(tmp: Path, target_dir: Path, comm: MPI.Comm):
    comm.Barrier()
    if comm.rank == 0:
        for f in sorted(tmp.iterdir()):
            os.replace(f, target_dir / f.name)
        shutil.rmtree(tmp, ignore_errors=True)
    comm.Barrier()


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(f"not JSON serialisable: {type(x)}")


def _write_on_root(path, write, comm: MPI.Comm) -> None:
    """Rank 0 calls ``write(tmp_path)``; the file is then renamed to ``path``."""
    path = Path(path)
    tmp = _tmpdir(path, comm)
    try:
        if comm.rank == 0:
            write(tmp / path.name)
    except BaseException:
        _discard(tmp, comm)
        raise
    _commit(tmp, path.parent, comm)


def write_json(path, data: dict, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Write ``data`` as JSON to ``path`` atomically (rank 0 writes)."""
    def write(p):
        with open(p, "w") as fh:
            json.dump(data, fh, indent=2, default=_jsonable)
            fh.write("\n")
    _write_on_root(path, write, comm)


def write_npz(path, arrays: dict, comm: MPI.Comm = MPI.COMM_WORLD) -> None:
    """Write numpy arrays (the same on every rank) to ``path`` (.npz) atomically."""
    def write(p):
        with open(p, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    _write_on_root(path, write, comm)


def write_xdmf(path, mesh, functions=(), meshtags=(), node_displacement=None,
               comm: MPI.Comm | None = None) -> None:
    """Write ``mesh`` (optionally moved by ``node_displacement`` (n_nodes, 3) mm, given per
    geometry node) with functions and mesh tags to ``path`` (.xdmf + .h5), atomically."""
    import dolfinx.io

    comm = comm or mesh.comm
    path = Path(path)
    tmp = _tmpdir(path, comm)
    x = mesh.geometry.x
    if node_displacement is not None:
        x[:, :3] += node_displacement
    try:
        with dolfinx.io.XDMFFile(comm, str(tmp / path.name), "w") as f:
            f.write_mesh(mesh)
            for tags in meshtags:
                f.write_meshtags(tags)
            for fn in functions:
                f.write_function(fn)
    except BaseException:
        _discard(tmp, comm)
        raise
    finally:
        if node_displacement is not None:
            x[:, :3] -= node_displacement
    _commit(tmp, path.parent, comm)
