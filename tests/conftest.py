"""Shared fixtures: tiny synthetic scenes, built once per session (dolfinx conftest habits);
the test tiers.

Every test belongs to one tier, a marker (``pytest -m unit``; ``make check`` runs the unit
tier, ``make test`` all of them):

* ``unit``: one part on its own (a unit cube, a block, a function): seconds, no head;
* ``integration``: the engine and the planner on the tiny synthetic heads, in this process;
* ``scripts``: the scripts as a user chains them, in fresh processes (the CTs among them);
* ``browser``: the explorer's page in headless Chromium;
* ``clients``: the files the scripts write, opened by ParaView's ``pvbatch``.

A test's tier is its own marker, else its module's ``TIER``, else ``integration`` where it
uses a tiny head (the ``tiny_anatomy`` fixture, directly or not) and ``unit`` where it does
not. ``mpi`` (runs ``mpirun -n 2`` itself) is marked besides the tier.
"""

import gc
import os

import numpy as np
import pytest

TIERS = ("unit", "integration", "scripts", "browser", "clients")

if "PYTEST_XDIST_WORKER" in os.environ:
    # `make test` runs a worker per core: an ``mpirun -n 2`` a test starts shares the cores
    # with the other worker, and Open MPI's busy-waiting ranks would take turns spinning
    os.environ.setdefault("OMPI_MCA_mpi_yield_when_idle", "1")


def pytest_collection_modifyitems(config, items):
    """Give each test its tier marker (module docstring); skip the ``cgal`` tests (a scene
    meshed from a CT) where pygalmesh is not installed (PyPI has no wheel of it)."""
    import importlib.util

    no_cgal = importlib.util.find_spec("pygalmesh") is None
    for item in items:
        if no_cgal and "cgal" in item.keywords:
            item.add_marker(pytest.mark.skip(reason="pygalmesh (CGAL's mesher) is not "
                                             "installed: no scene from a CT"))
        own = [m.name for m in item.own_markers if m.name in TIERS]
        if len(own) > 1:
            raise pytest.UsageError(f"{item.nodeid}: more than one tier {own}")
        tier = own[0] if own else getattr(item.module, "TIER", None) or (
            "integration" if "tiny_anatomy" in item.fixturenames else "unit")
        if tier not in TIERS:
            raise pytest.UsageError(f"{item.nodeid}: unknown tier {tier!r}")
        if not own:
            item.add_marker(tier)


@pytest.fixture(autouse=True)
def _collective_cleanup():
    """Collective destructors line up across ranks (dolfinx python/test/conftest.py)."""
    # imported here, in the workers: pytest-xdist's controller loads this file and must not
    # become an MPI process (its singleton's OMPI_* and PMIX_* variables, inherited by the
    # workers, make every mpirun a test starts exit 1 at once)
    from mpi4py import MPI

    yield
    gc.collect()
    MPI.COMM_WORLD.Barrier()


@pytest.fixture(scope="session")
def tiny_anatomy():
    from meshes.synthetic import synthetic_head

    return synthetic_head("class3", "tiny")


#: Newton to 1e-10: the equilibrium options of `tight_scene`.
TIGHT = dict(method="newton", xtol=1e-10, frtol=1e-10)


def _mandible_only(anatomy, **kw):
    from inverse.scene import Scene
    from inverse.treatment import rigid_treatment

    return Scene(anatomy, treatment=rigid_treatment(("mandible",)), **kw)


@pytest.fixture(scope="session")
def mandible_only():
    """``mandible_only(anatomy, **kw)``: a new `Scene` with the six mandible motions only
    (``kw`` go to Scene)."""
    return _mandible_only


@pytest.fixture(scope="session")
def _mandible_session(tiny_anatomy):
    scene = _mandible_only(tiny_anatomy)
    scene.case, scene.resolution = "class3", "tiny"
    return scene


@pytest.fixture
def mandible_scene(_mandible_session):
    """class3/tiny with the six mandible motions only (built once per session); back at rest
    after each test, also when it fails (free where it is at rest)."""
    yield _mandible_session
    _mandible_session.solve(np.zeros(6))


@pytest.fixture(scope="session")
def _tight_scenes(tiny_anatomy):
    """{(contact, material): scene} of `tight_scene`, built on first use."""
    scenes = {}

    def get(contact, material="homogeneous"):
        key = (contact, material)
        if key not in scenes:
            scenes[key] = _mandible_only(tiny_anatomy, equilibrium=TIGHT, contact=contact,
                                         material=material)
            scenes[key].case, scenes[key].resolution = "class3", "tiny"
        return scenes[key]
    return get


@pytest.fixture
def tight_scene(_tight_scenes):
    """class3/tiny, six mandible motions, the lips glued to the teeth (a synthetic head's
    default), solved by Newton to tolerances far below the defaults (for rate, Taylor and
    finite-difference checks); back at rest afterwards."""
    scene = _tight_scenes("glued")
    yield scene
    scene.solve(np.zeros(6))


@pytest.fixture
def tight_sliding(_tight_scenes):
    """`tight_scene` with the lips sliding on the teeth."""
    scene = _tight_scenes("sliding")
    yield scene
    scene.solve(np.zeros(6))


def _central_differences(scene, obj, p, h: float = 1e-3) -> np.ndarray:
    """d(points)/dp (3 Nt, Np) of ``obj`` at ``p`` by central differences (2 Np solves);
    the scene is left at ``p``."""
    p = np.asarray(p, dtype=float)
    cols = []
    for e in np.eye(len(p)) * h:
        scene.solve(p + e)
        xp = obj.points().ravel()
        scene.solve(p - e)
        cols.append((xp - obj.points().ravel()) / (2 * h))
    scene.solve(p)
    return np.stack(cols, axis=1)


@pytest.fixture(scope="session")
def central_differences():
    """``central_differences(scene, obj, p, h=1e-3)``: d(points)/dp (3 Nt, Np) of an
    objective's points by central differences; the scene is left at p."""
    return _central_differences


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def tight_tissues(_tight_scenes):
    """`tight_sliding` with the tissue classes' materials (skin, fat, lean tissue)."""
    scene = _tight_scenes("sliding", "tissues")
    yield scene
    scene.solve(np.zeros(6))
