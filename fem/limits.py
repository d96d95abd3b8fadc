"""Every user option's allowed range, the floors of solver tolerances and the ceilings of
iteration counts, in one place: no input can make a run unbounded.

The scripts check their options with `check` before any work; the Python API checks the same
values where it takes them and raises the same `InputError`.

Why a run stays bounded: every solver loop counts iterations against a ceiling below (SNES
``max_it`` ≤ `MAX_SNES_ITERATIONS`; at most `MAX_BISECTIONS` continuation bisections, 3
stall refreshes and 4 diagonal-shift retries per solve; a plan ≤ `MAX_PLAN_ITERATIONS`
Gauss-Newton iterations of at most 6 × (`MAX_BACKTRACKS` + 1) line-search trials), and no
tolerance can be tightened below its floor (`XTOL_FLOOR_MM`: a plan's forward xtol, ``ftol``
× the mean landmark distance, is floored there when the targets are reached; `FRTOL_FLOOR`
for the residual).
"""

from __future__ import annotations

import dataclasses
import math

from meshes.errors import InputError

#: Smallest forward step tolerance, mm: Newton reaches it from any converging start in 1-2
#: quadratic steps (the tests' tight solves use it); below it roundoff decides.
XTOL_FLOOR_MM = 1e-10
#: Smallest residual a solve asks for, relative to the goals' whole load |df/dg g(p)|: a
#: step of 1e-8 in p (a plan's last Gauss-Newton step on exactly reachable targets) otherwise
#: asked for a residual below roundoff, and Newton ran out of iterations at every bisection.
FRTOL_FLOOR = 1e-12
#: Smallest relative decrease of T a plan may stop at. A plan's forward solves go to ftol ×
#: the mean landmark distance (floored at `XTOL_FLOOR_MM`): with ftol = 2.5e-184 a tiny plan
#: ran Newton to 1e-10 mm in every trial and crept on for over a minute.
FTOL_FLOOR = 1e-12
#: Most iterations of one SNES solve a user may ask for (defaults: quasi-Newton 40, Newton 25).
MAX_SNES_ITERATIONS = 1000
#: Most bisections of the step in p in one solve (default 6: 1/64 of the step).
MAX_BISECTIONS = 20
#: Most Gauss-Newton iterations of a plan (plans converge in 2-8).
MAX_PLAN_ITERATIONS = 1000
#: Most halvings of a Gauss-Newton step in one line search (default 8).
MAX_BACKTRACKS = 30
#: An equilibrium whose smallest volume ratio det F is below this is reported: "tissue
#: compressed to N %". Moves within the bounds kept det F >= 0.61 (stress table, 14 mm
#: advance: coarse 0.61, medium 0.63); a 20 mm advance (beyond the 15 mm bound) fell to 0.50
#: (coarse) and 0.42 (paper), a 60 mm one to 0.23.
COMPRESSION_WARN = 0.5


@dataclasses.dataclass(frozen=True)
class Range:
    """An allowed interval; ``open_lo``/``open_hi`` exclude the end; ``integer`` values."""

    lo: float
    hi: float
    open_lo: bool = False
    open_hi: bool = False
    integer: bool = False

    def text(self) -> str:
        lo = "(" if self.open_lo else "["
        hi = ")" if self.open_hi else "]"
        kind = "an integer" if self.integer else "a number" if math.isinf(self.hi) \
            else "a finite number"
        return f"{kind} in {lo}{self.lo:g}, {self.hi:g}{hi}"

    def contains(self, v: float) -> bool:
        return ((math.isfinite(v) or v == self.hi)
                and (v > self.lo if self.open_lo else v >= self.lo)
                and (v < self.hi if self.open_hi else v <= self.hi)
                and (not self.integer or float(v).is_integer()))


#: The options (script flag names without dashes, Python keywords alike).
OPTIONS = {
    "ftol": Range(FTOL_FLOOR, 1.0, open_hi=True),               # relative decrease of T
    "max_iterations": Range(1, MAX_PLAN_ITERATIONS, integer=True),
    "tikhonov": Range(0.0, 1e6),                                # α, mm² per unit²
    "penalty": Range(0.0, 1e12, open_lo=True),    # k, kPa/mm (the stress sweep: 1e6 × 5e4)
    "substep_mm": Range(0.0, math.inf, open_lo=True),           # mm; inf: one step
    "iterations": Range(1, 100, integer=True),                  # relax steps per substep
    "scale": Range(-1e3, 1e3),                                  # --scales entries
    "port": Range(0, 65535, integer=True),                      # 0: any free port
    "xtol": Range(XTOL_FLOOR_MM, 100.0),                        # mm
    "max_it": Range(1, MAX_SNES_ITERATIONS, integer=True),
    "max_bisections": Range(0, MAX_BISECTIONS, integer=True),
    # the equilibrium's (`fem.policy.EquilibriumOptions`; xtol and max_it above)
    "frtol": Range(FRTOL_FLOOR, 1.0),                           # of the step's load
    "atol": Range(0.0, 1e6),                                    # residual norm, mN
    "shift_max": Range(0.0, 1e12, open_lo=True),                # x the median diagonal of K
    "shift_retry": Range(0.0, 1e12),
    "lag_its": Range(0, MAX_SNES_ITERATIONS, integer=True),
    "quadrature_degree": Range(0, 12, integer=True),
    # a plan's (`inverse.planner.PlanOptions`)
    "gtol": Range(0.0, 1e6),                                    # mm² per unit
    "step_tol": Range(0.0, 100.0),                              # units (mm, degrees)
    "mu": Range(0.0, 1e12),   # relative to diag(H); a resumed plan starts from its last mu
    "armijo": Range(0.0, 0.5, open_lo=True, open_hi=True),
    "max_backtracks": Range(0, MAX_BACKTRACKS, integer=True),
    "max_step": Range(0.0, 1e3, open_lo=True),                  # mm or degrees
}


def check(name: str, value, flag: str | None = None, ranges: dict | None = None,
          numbers_only: bool = False):
    """``value`` if it lies in ``ranges[name]`` (default `OPTIONS`), else `InputError`
    naming ``flag`` (default the keyword) and the allowed range. A script's option may be
    the text of a number; ``numbers_only`` (a setting made in code) refuses text."""
    r = (OPTIONS if ranges is None else ranges)[name]
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if isinstance(value, bool) or (numbers_only and not isinstance(value, (int, float))) \
            or not r.contains(v):
        raise InputError(f"{flag or name} must be {r.text()}, got {value!r}")
    return int(v) if r.integer else v
