"""One builder for every GP-SLAM NLP: a motion model and a field model, each a plug-in.

:func:`build_slam` asks, in order:

1. the motion model (:class:`MotionModel`: translational, planar with heading, IMU) to
   declare its unknowns, its data and every setting it reads, and its cost blocks
   (odometry or IMU increments, bias walk, initial state). It returns a :class:`Pose`:
   the positions of the field samples as an expression, where their unknowns sit in the
   NLP, and, when the magnetometer turns with the body, the body-to-map rotation;
2. the field model (:class:`FieldModel`, casmag.model.field: the exact GP at the samples or
   a reduced-rank map, no map at all for the IMU-only adjustment) to declare its unknowns
   and the blocks ``magnetometer``, ``gp_prior``, ``gp_logdet``, ``constant_field_prior``
   (or a window's ``map_prior``) on that pose, and to return its Hessian callback;
3. the motion model to close the problem with the blocks that come last (the anchor and
   the bias prior of the translational model); no symbol is declared there, because the
   field's numpy blocks see the vectors declared before them;

and creates one IPOPT solver: CasADi's exact Hessian of the smooth blocks, J^T J of every
block declared as a residual (:meth:`casmag.nlp.NLPBuilder.residual`) and the field's
callback for its own blocks. A new motion model is one class with :meth:`MotionModel.declare`
(and :meth:`MotionModel.close` when it needs it); every field model serves it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import casadi as ca

from casmag import memory
from casmag.model.knots import Knots
from casmag.nlp import NLP, NLPBuilder
from casmag.problem.spec import SolverSpec

#: A field's Hessian callback for ``hess_lag``: (block name or names, callback).
HessianPart = tuple[str | tuple[str, ...], Any]


@dataclass
class Rotation:
    """The body-to-map rotation of each field sample: R_k = function(unknowns[k], aux[k]),
    with ``unknowns`` (n, r) a variable of the NLP and ``aux`` (n, a) a parameter (the
    nominal rotation of an error state) or None."""

    function: ca.Function
    unknowns: ca.MX
    variable: str
    aux: ca.MX | None = None
    aux_name: str | None = None


@dataclass
class Pose:
    """What a motion model gives the field model.

    positions: (n, dim) positions of the field samples; variable: the NLP variable holding
    their unknowns, ``nominal``: the parameter they are added to (dead reckoning, nominal
    trajectory), None when the variable holds the positions themselves; knots: how the
    variable's rows map to samples (one per sample unless interpolated); rotation: None when
    the magnetometer is read in the map frame (y = m(p)), else y = R^T m(p)."""

    positions: ca.MX
    n: int
    dim: int
    variable: str
    nominal: str | None
    knots: Knots
    rotation: Rotation | None = None
    own: dict[str, ca.MX] = field(default_factory=dict)  # the motion model's symbols for close()


class MotionModel(ABC):
    """A motion model: its unknowns, data and cost blocks, and the pose of the samples."""

    #: Short name, used in the solver's name.
    name: str = "motion"

    @abstractmethod
    def declare(self, b: NLPBuilder) -> Pose:
        """Declare every variable and parameter of the motion model and its cost blocks."""

    def close(self, b: NLPBuilder, pose: Pose) -> None:
        """Cost blocks added after the field's (declare no symbol here); none by default."""
        return None

    def solver(self, solver: SolverSpec) -> SolverSpec:
        """IPOPT settings this model's structure needs (default: the problem's)."""
        return solver


class FieldModel(ABC):
    """A field model: the map's unknowns and blocks on the samples of a pose."""

    name: str = "field"

    @abstractmethod
    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        """Declare the map's symbols and blocks; return its Hessian callback (or None)."""

    def solver(self, solver: SolverSpec) -> SolverSpec:
        """IPOPT settings this field's structure needs (default: the problem's)."""
        return solver


@dataclass(frozen=True)
class NoField(FieldModel):
    """No map: the motion model alone (the IMU-only adjustment, dead reckoning smoothing)."""

    name = "only"

    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        return None


@dataclass(frozen=True)
class LoopClosures(FieldModel):
    """No map, but pairs of samples known to be at the same place (loop closures, e.g.
    casmag.solver.closures): the block ``closure``, 0.5 sum |(p_j - p_i) / sigma_closure|^2
    over the pairs (i, j), a residual (linear, so its Gauss-Newton Hessian is exact), with
    ``sigma_closure`` a parameter. The motion model's adjustment with the loops closed: the
    start of GP-SLAM where the dead reckoning has drifted by more than a lengthscale
    between visits. Serves every motion model (it reads only the pose's positions)."""

    pairs: tuple[tuple[int, int], ...]
    name = "closures"

    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        sigma = b.parameter("sigma_closure", (1, 1))
        first = [i for i, _ in self.pairs]
        second = [j for _, j in self.pairs]
        P = pose.positions
        b.residual("closure", (P[second, :] - P[first, :]) / sigma)
        return None


#: NLPs built by this process, per ``<motion>_<field>`` name (tests count them).
BUILDS: Counter[str] = Counter()


@lru_cache(maxsize=24)
def cached_slam(motion: MotionModel, field: FieldModel, solver: str) -> NLP:
    """:func:`build_slam` once per process for each motion model, field model and solver
    settings (as JSON): the motion and field models are frozen dataclasses whose fields are
    everything that changes the symbolic problem, so every seed, data set and parameter
    value of one structure shares one build."""
    return build_slam(motion, field, SolverSpec.model_validate_json(solver))


def uncached_slam(motion: MotionModel, field: FieldModel, solver: str) -> NLP:
    """:func:`cached_slam`'s build without keeping it: for a structure solved once, whose
    NLP (with IPOPT's and the Hessian callbacks' memory) the cache would hold on to."""
    return build_slam(motion, field, SolverSpec.model_validate_json(solver))


def build_slam(motion: MotionModel, field: FieldModel, solver: SolverSpec) -> NLP:
    """The MAP problem of a motion model and a field model as one NLP (use
    :func:`cached_slam` to build each structure once)."""
    BUILDS[f"{motion.name}_{field.name}"] += 1
    b = NLPBuilder()
    solver = field.solver(motion.solver(solver))
    pose = motion.declare(b)
    with memory.build_budget(memory.budget_bytes(solver.memory_budget)):
        hessian = field.declare(b, pose, solver)
    motion.close(b, pose)
    return b.build(
        solver,
        name=f"casmag_{motion.name}_{field.name}",
        gauss_newton=hessian,
        residuals=b.gauss_newton_residuals(solver.hessian),
    )
