"""What one target (Debian's dolfinx 0.5.2 or PyPI's 0.11) answers on one scene file, as JSON
on stdout: a forward solve's landmarks, the adjoint gradient of a landmark objective, the
landmark sensitivities dx/dp, and a whole plan back to the forward solve's landmarks, every
equilibrium by Newton to 1e-10 mm. `test_targets` runs it on both targets and compares.

    python tests/target_answers.py scene.vtu
"""

from mpi4py import MPI

import json
import sys

from inverse.scene import Scene
from meshes.external import load_tet_mesh

#: Newton to 1e-10 (conftest's TIGHT): the answers are the discrete model's, not a solver's.
TIGHT = dict(method="newton", xtol=1e-10, frtol=1e-10)
#: The treatment (mm, degrees): a BSSO advance with some rotation.
P = {"mandible.advance_mm": 4.0, "mandible.vertical_mm": -1.0, "mandible.pitch_deg": 2.0}


def answers(mesh: str) -> dict:
    scene = Scene(lambda: load_tet_mesh(mesh), equilibrium=TIGHT, params_used=list(P),
                  contact="glued")
    names = sorted(scene.domain.landmarks)
    scene.solve(scene.param_vector(P), tangent=True)
    forward = scene.landmarks(names)
    targets = {k: v.tolist() for k, v in forward.items()}
    moved = {k: (v + [0.5, 0.0, 0.0]).tolist() for k, v in forward.items()}
    obj = scene.objective(moved, names)
    S, _ = obj.jacobian("direct")
    gradient = obj.gradient()
    plan = scene.plan(targets, names, tikhonov=0.0, ftol=1e-12, gtol=1e-14, xtol=1e-10)
    return {"forward": {k: v.tolist() for k, v in forward.items()},
            "gradient": gradient.tolist(), "sensitivity": S.tolist(),
            "plan_p": plan.params.tolist(),
            "plan": {k: v.tolist() for k, v in scene.landmarks(names).items()},
            "dofs": scene.domain.n_dofs}


if __name__ == "__main__":
    out = answers(sys.argv[1])
    if MPI.COMM_WORLD.rank == 0:
        print(json.dumps(out))
