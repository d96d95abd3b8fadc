"""``bench.py peers``: orthodiff beside the usual way of doing each job, in the same run.

For each resolution and rank count, one process under ``mpirun -n N`` (this file run as a
worker) measures, on the same scene, treatment and goal:

* **forward** (class3, 5 mm mandible advance from rest): orthodiff's default solve against
  the FEniCSx tutorial recipe on orthodiff's own forms and mesh (dolfinx ``NonlinearProblem``
  + ``NewtonSolver``, MUMPS LU, incremental criterion 1e-8); the landmarks' agreement;
* **gradient** (class3's goal at that equilibrium, both at xtol 1e-6 mm): one adjoint solve
  against forward finite differences (Np + 1 forward solves, h = 1e-3 unit); their agreement;
* **planning** (class3-asym, default goal, `PLAN_PARAMS`, α = `TIKHONOV`, ftol = `FTOL`):
  Sparse Gauss-Newton (`scripts/plan.py`'s) against Levenberg-Marquardt with
  finite-difference Jacobians (FEBio's optimize module does this: Np + 1 forward solves an
  iteration, here on orthodiff's solver at xtol 1e-5 mm); T reached and the parameters'
  agreement.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: FD step (mm or degrees) and the forward tolerance of the FD solves (mm).
FD_H, FD_XTOL = 1e-3, 1e-6
#: Levenberg-Marquardt: FD step, forward tolerance, start damping, iterations at most.
LM_H, LM_XTOL, LM_MU, LM_MAX_IT = 1e-2, 1e-5, 1e-3, 30


def _timed(f):
    t = time.perf_counter()
    out = f()
    return out, time.perf_counter() - t


def _forward(res: str, comm) -> dict:
    from fem.verification import lu_newton
    from inverse.scene import Scene
    from inverse.treatment import PLAN_PARAMS

    scene = Scene.from_case("class3", res, params_used=PLAN_PARAMS, comm=comm)
    p = scene.param_vector({"mandible.advance_mm": 5.0})
    st, ours = _timed(lambda: scene.solve(p))
    lm_ours = scene.landmarks()
    eq = scene.eq
    eq.set_params(p)
    eq.u.x.array[:] = 0.0
    eq.u.x.scatter_forward()
    solver = lu_newton(eq.ufl_forms["residual"], eq.u, eq.bcs, eq.ufl_forms["jacobian"],
                       convergence_criterion="incremental", rtol=1e-8, max_it=50)
    (its, converged), peer = _timed(lambda: solver.solve(eq.u))
    lm_peer = scene.landmarks()
    diff = max(float(abs(lm_ours[k] - lm_peer[k]).max()) for k in lm_ours)
    out = {"ours_s": ours, "ours_its": st.iterations, "peer_s": peer,
           "peer_its": int(its), "peer_converged": bool(converged), "landmarks_mm": diff}
    scene.eq.destroy()
    return out


def _gradient(res: str, comm) -> dict:
    import numpy as np

    from inverse.scene import Scene
    from inverse.treatment import PLAN_PARAMS, TIKHONOV

    scene = Scene.from_case("class3", res, params_used=PLAN_PARAMS, comm=comm,
                            equilibrium=dict(xtol=FD_XTOL))
    obj = scene.objective(scene.default_targets(), tikhonov=TIKHONOV)
    p = scene.param_vector({"mandible.advance_mm": 5.0})
    scene.solve(p, tangent=True)
    g, adjoint = _timed(obj.gradient)
    T0 = obj.value()

    def fd():
        out = np.zeros(len(p))
        for i in range(len(p)):
            q = p.copy()
            q[i] += FD_H
            scene.solve(q)
            out[i] = (obj.value() - T0) / FD_H
        return out
    g_fd, fd_s = _timed(fd)
    rel = float(np.linalg.norm(g_fd - g) / max(np.linalg.norm(g), 1e-300))
    scene.eq.destroy()
    return {"adjoint_s": adjoint, "fd_s": fd_s, "fd_solves": len(p) + 1, "rel_diff": rel}


def _lm(scene, obj):
    """Levenberg-Marquardt with forward-difference Jacobians on T = ½|r|² + ½α|p|²."""
    import numpy as np

    from inverse.treatment import FTOL

    eq = scene.eq
    eq.set_xtol(LM_XTOL)
    lo, hi = scene.treatment.bounds.T
    a = np.sqrt(obj.tikhonov)
    w = np.sqrt(obj.weights.ravel())

    def resid(q):
        scene.solve(q)
        return np.concatenate([w * obj.residual().ravel(), a * q])
    p = np.zeros(eq.n_params)
    r, mu, solves, its = resid(p), LM_MU, 1, 0
    T = 0.5 * float(r @ r)
    for its in range(1, LM_MAX_IT + 1):
        J = np.empty((len(r), len(p)))
        for i in range(len(p)):
            q = p.copy()
            q[i] += LM_H
            J[:, i] = (resid(q) - r) / LM_H
        solves += len(p)
        H, g = J.T @ J, J.T @ r
        while True:
            dp = np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-12), -g)
            q = np.clip(p + dp, lo, hi)
            r_q = resid(q)
            solves += 1
            T_q = 0.5 * float(r_q @ r_q)
            if T_q < T or mu > 1e6:
                break
            mu *= 10
        mu = max(mu / 10, 1e-9)
        done = T - T_q <= FTOL * T
        p, r, T = q, r_q, min(T, T_q)
        if done:
            break
    return p, T, its, solves


def _planning(res: str, comm) -> dict:
    import numpy as np

    from inverse.scene import Scene
    from inverse.treatment import PLAN_PARAMS, TIKHONOV

    scene = Scene.from_case("class3-asym", res, params_used=PLAN_PARAMS, comm=comm)
    result, sgn = _timed(lambda: scene.plan())
    obj = scene.objective(scene.default_targets(), tikhonov=TIKHONOV)
    scene.solve(np.zeros(len(scene.param_names)))
    (p, T, its, solves), lm = _timed(lambda: _lm(scene, obj))
    scene.eq.destroy()
    return {"sgn_s": sgn, "sgn_its": result.gn_iterations, "sgn_solves": result.forward_solves,
            "sgn_T": result.objective, "lm_s": lm, "lm_its": its, "lm_solves": solves,
            "lm_T": T, "p_diff": float(np.abs(p - result.params).max())}


def work(res: str) -> None:
    """One worker (under mpirun): every peer at ``res``; JSON on stdout (rank 0)."""
    from mpi4py import MPI  # first: it loads the MPI library PETSc links (PyPI's MPICH)
    from petsc4py import init as petsc_init

    petsc_init([sys.argv[0]])

    from scripts._bench import result

    comm = MPI.COMM_WORLD
    result({"forward": _forward(res, comm), "gradient": _gradient(res, comm),
            "planning": _planning(res, comm)}, comm)


def peers(args) -> None:
    from scripts._bench import (
        goal,
        header,
        ranks_label,
        series_plot,
        table,
        worker,
        write_section,
    )

    rows = {"forward": [], "gradient": [], "planning": []}
    speedups, goals = {}, []   # speedups: label -> [(resolution, peer s / orthodiff s)]
    for res in args.resolutions.split(","):
        for n in (int(r) for r in args.ranks.split(",")):
            m = worker(__file__, n, res)
            if "error" in m:
                for k in rows:
                    rows[k].append([res, n, m["error"]])
                continue
            f, g, p = m["forward"], m["gradient"], m["planning"]
            rows["forward"].append([res, n, f"**{f['ours_s']:.2f}** ({f['ours_its']})",
                                    f"{f['peer_s']:.2f} ({f['peer_its']})",
                                    f"**{f['peer_s'] / f['ours_s']:.1f}x**",
                                    f"{f['landmarks_mm']:.1e}"])
            rows["gradient"].append([res, n, f"**{g['adjoint_s']:.3f}**",
                                     f"{g['fd_s']:.2f} ({g['fd_solves']})",
                                     f"**{g['fd_s'] / g['adjoint_s']:.0f}x**",
                                     f"{g['rel_diff']:.1e}"])
            rows["planning"].append([res, n, f"**{p['sgn_s']:.1f}** ({p['sgn_its']}, "
                                     f"{p['sgn_solves']})", f"{p['lm_s']:.1f} ({p['lm_its']}, "
                                     f"{p['lm_solves']})", f"**{p['lm_s'] / p['sgn_s']:.1f}x**",
                                     f"{p['sgn_T']:.3g} / {p['lm_T']:.3g}",
                                     f"{p['p_diff']:.2g}"])
            print(res, n, m, flush=True)
            for k, ratio in (("tutorial recipe / forward", f["peer_s"] / f["ours_s"]),
                             ("finite differences / adjoint", g["fd_s"] / g["adjoint_s"]),
                             ("LM + FD / Sparse Gauss-Newton", p["lm_s"] / p["sgn_s"])):
                speedups.setdefault(f"{k}, {ranks_label(n)}", []).append((res, ratio))
            if res == "paper" and n == 2:
                goals = [goal("forward against the FEniCSx tutorial recipe, paper, 2 ranks "
                              "(peers)", f["ours_s"], "s", peer=f["peer_s"],
                              note=f"landmarks agree to {f['landmarks_mm']:.1e} mm"),
                         goal("gradient against finite differences, paper, 2 ranks (peers)",
                              g["adjoint_s"], "s", peer=g["fd_s"],
                              note=f"agree to {g['rel_diff']:.1e}"),
                         goal("plan against LM with FD Jacobians, paper, 2 ranks (peers)",
                              p["sgn_s"], "s", peer=p["lm_s"],
                              note=f"T {p['sgn_T']:.3g} / {p['lm_T']:.3g} mm²")]
    body = header("Peers, side by side in one run", args) + [
        "Each row: one process under `mpirun -n ranks` (`scripts/bench_peers.py`), the same "
        "scene, treatment and goal for both. **Forward** (class3, 5 mm mandible advance from "
        "rest): orthodiff's default solve (quasi-Newton on one kept factorisation, xtol "
        "0.005 mm) against the FEniCSx tutorial recipe on the same forms and mesh "
        "(`NonlinearProblem` + `NewtonSolver`, MUMPS LU, incremental 1e-8); seconds "
        "(iterations), the ratio, and the largest landmark difference.", ""]
    body += table(["resolution", "ranks", "orthodiff s (its)", "tutorial recipe s (its)",
                   "ratio", "landmarks differ mm"], rows["forward"])
    body += ["", f"**Gradient** of class3's goal at that equilibrium (both at xtol {FD_XTOL:g} "
             f"mm): one adjoint solve against forward differences (h = {FD_H:g}, Np + 1 "
             "forward solves); the relative difference |g_FD − g| / |g|.", ""]
    body += table(["resolution", "ranks", "adjoint s", "finite differences s (solves)",
                   "ratio", "relative difference"], rows["gradient"])
    body += ["", "**Planning** (class3-asym, default goal, the ten planning parameters, the "
             "same α and ftol): Sparse Gauss-Newton (`Scene.plan`, exact sensitivities) "
             "against Levenberg-Marquardt with forward-difference Jacobians (FEBio's optimize "
             f"module's method: Np + 1 forward solves an iteration; h = {LM_H:g}, solves at "
             f"xtol {LM_XTOL:g} mm); seconds (iterations, forward solves), T reached (mm²) "
             "and the largest parameter difference.", ""]
    body += table(["resolution", "ranks", "Sparse Gauss-Newton s (its, solves)",
                   "LM + FD s (its, solves)", "ratio", "T: SGN / LM", "p differ"],
                  rows["planning"])
    png = series_plot("peers", speedups, "resolution", "peer time / orthodiff time")
    body += ["", f"![peers]({png})"]
    write_section("peers", "\n".join(body), goals)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    work(sys.argv[1])
