"""Algorithm 1 of the paper: the online iterative flange calibration.

Owns the pool of four pairs and its optimum. The pool starts with four pairs
(line 2); each new pair (line 5) is tried in place of each of the four
(lines 6-8), each candidate pool is solved by Eq. 9-12 and scored by the cost
of its e_icp (Eq. 13); the best candidate replaces the pool when its cost is
strictly lower than the optimum's (lines 9-13). The run stops when the cost
reaches ``e_required`` or after ``k_max`` new pairs (line 4).

On lines 6-15: taken literally, a replacement accepted at slot i would be
tried again at slots i+1.., putting the same pair twice in the pool. The
reference implementation (the authors' toolbox) instead keeps the best of the
candidate pools that beat the optimum, which is what this module does.

:class:`Algorithm1` is fed one pair at a time (the daemon's online use);
:func:`run_algorithm1` is the batch helper. The scoring is a callable
``T_base_cam -> IcpMetric`` (an :class:`~celld.calib.metrics.IcpVerifier`):
this module never sees a cloud nor a ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from celld.calib.metrics import IcpMetric, translation_cost
from celld.calib.rigid import Array, RigidFit, check_pairs, solve_rigid
from celld.errors import CalibrationError, InputError
from celld.schemadoc import array, boolean, integer, number, obj, string, texts

# Size of the pool (line 2 of Algorithm 1).
POOL_SIZE = 4

Evaluate = Callable[[Array], IcpMetric]
Cost = Callable[[IcpMetric], float]


@dataclass(frozen=True)
class Candidate:
    """One candidate pool: the new pair in ``slot`` (None: the initial pool)."""

    slot: int | None
    fit: RigidFit | None  # Eq. 9-12 on the pool (residuals, uncertainty); None when degenerate
    e_icp: IcpMetric
    cost: float
    reason: str = ""  # why the candidate has no estimate

    @property
    def T_base_cam(self) -> Array | None:
        return None if self.fit is None else self.fit.T_dst_src


@dataclass(frozen=True)
class Algorithm1Step:
    """The state after one step (k = 0: the initial pool, line 3).

    Attributes
    ----------
    k : int
        Number of new pairs taken so far.
    pair_id : str | None
        The new pair of this step (None for the initial pool).
    candidates : tuple of Candidate
        Every pool tried at this step, with its e_icp and cost.
    accepted_slot : int | None
        The slot the new pair took, or None when the pool was kept.
    pool_ids : tuple of str
        The pool after the step.
    fit : RigidFit | None
        The optimum after the step, with the pool's residuals and uncertainty
        (None while every pool so far was degenerate).
    e_optimal : IcpMetric
    cost_optimal : float
    reached : bool
        ``cost_optimal <= e_required``.
    """

    k: int
    pair_id: str | None
    candidates: tuple[Candidate, ...]
    accepted_slot: int | None
    pool_ids: tuple[str, ...]
    fit: RigidFit | None
    e_optimal: IcpMetric
    cost_optimal: float
    reached: bool

    @property
    def T_base_cam(self) -> Array | None:
        return None if self.fit is None else self.fit.T_dst_src

    def as_dict(self) -> dict[str, object]:
        return {
            "k": self.k,
            "pair": self.pair_id,
            "candidate_costs_mm": [c.cost * 1e3 if math.isfinite(c.cost) else None for c in self.candidates],
            "accepted_slot": self.accepted_slot,
            "pool": list(self.pool_ids),
            "cost_mm": self.cost_optimal * 1e3 if math.isfinite(self.cost_optimal) else None,
            "reached": self.reached,
        }


# The JSON shape of Algorithm1Step.as_dict.
STEP_SCHEMA = obj(
    "The state after one step of Algorithm 1 (k = 0: the initial pool).",
    {
        "k": integer(lo=0),
        "pair": string("The pair this step tried (null for the initial pool).", null=True),
        "candidate_costs_mm": array(number(null=True), "The cost of each candidate pool, null where it had no estimate."),
        "accepted_slot": integer("The slot the pair took (null: none, or the initial pool).", lo=0, null=True),
        "pool": texts("The pool after the step."),
        "cost_mm": number("Its cost, null when infinite.", null=True),
        "reached": boolean("The cost is at or below e_required."),
    },
    ("k", "pair", "candidate_costs_mm", "accepted_slot", "pool", "cost_mm", "reached"),
)


@dataclass(frozen=True)
class Algorithm1Result:
    """Outcome of a run: the optimum (with its pool's residuals and uncertainty), its e_icp and the history."""

    fit: RigidFit | None
    e_optimal: IcpMetric
    cost: float
    pool_ids: tuple[str, ...]
    reached: bool
    steps: tuple[Algorithm1Step, ...]

    @property
    def T_base_cam(self) -> Array | None:
        return None if self.fit is None else self.fit.T_dst_src

    @property
    def n_pairs_used(self) -> int:
        """Pairs consumed: the initial four plus one per step."""
        return POOL_SIZE + self.steps[-1].k


class Algorithm1:
    """Algorithm 1, fed one pair at a time.

    Parameters
    ----------
    evaluate : callable
        ``T_base_cam -> IcpMetric``: e_icp of an estimate (Eq. 13).
    cost : callable
        ``IcpMetric -> float``: the cost metric (metres), e.g.
        :func:`~celld.calib.metrics.translation_cost`.
    e_required : float
        Target cost, metres.
    k_max : int
        Maximum number of new pairs after the initial four.
    with_scale : bool
        Estimate the scale ``c`` of Eq. 11 in each pool solve.
    """

    def __init__(
        self, evaluate: Evaluate, cost: Cost = translation_cost, *, e_required: float, k_max: int, with_scale: bool = False
    ) -> None:
        if not e_required >= 0.0:
            raise InputError(f"e_required: expected a cost >= 0 m, got {e_required}")
        if k_max < 0:
            raise InputError(f"k_max: expected >= 0 new pairs, got {k_max}")
        self._evaluate = evaluate
        self._cost = cost
        self.e_required = float(e_required)
        self.k_max = int(k_max)
        self._with_scale = with_scale
        self._pool_ids: list[str] = []
        self._P_base: np.ndarray = np.zeros((0, 3))
        self._P_cam: np.ndarray = np.zeros((0, 3))
        self._steps: list[Algorithm1Step] = []
        self._seen: set[str] = set()

    # -- state ---------------------------------------------------------------

    @property
    def started(self) -> bool:
        return bool(self._steps)

    @property
    def last(self) -> Algorithm1Step:
        if not self._steps:
            raise CalibrationError("Algorithm 1 has not started: give it four initial pairs first")
        return self._steps[-1]

    @property
    def reached(self) -> bool:
        return self.started and self.last.reached

    @property
    def done(self) -> bool:
        """True once the cost reached ``e_required`` or ``k_max`` pairs were taken (line 4)."""
        return self.started and (self.last.reached or self.last.k >= self.k_max)

    @property
    def steps(self) -> tuple[Algorithm1Step, ...]:
        return tuple(self._steps)

    def result(self) -> Algorithm1Result:
        s = self.last
        return Algorithm1Result(s.fit, s.e_optimal, s.cost_optimal, s.pool_ids, s.reached, tuple(self._steps))

    # -- steps ---------------------------------------------------------------

    def _score(self, slot: int | None, P_base: Array, P_cam: Array) -> Candidate:
        try:
            fit = solve_rigid(P_base, P_cam, with_scale=self._with_scale)
        except CalibrationError as exc:
            return Candidate(slot, None, IcpMetric.failed(str(exc)), math.inf, reason=str(exc))
        e = self._evaluate(fit.T_dst_src)
        return Candidate(slot, fit, e, float(self._cost(e)))

    def start(self, ids: Sequence[str], P_base: ArrayLike, P_cam: ArrayLike) -> Algorithm1Step:
        """Lines 1-3: the initial pool of four pairs, its estimate and e_icp."""
        if self._steps:
            raise CalibrationError("Algorithm 1 has already started")
        # A degenerate pool is scored (infinite cost, with the reason), not refused.
        P_b, P_c = check_pairs(P_base, P_cam, min_pairs=1, determined=False)
        if len(P_b) != POOL_SIZE or len(ids) != POOL_SIZE:
            raise InputError(f"initial pool: expected {POOL_SIZE} pairs and ids, got {len(P_b)} pairs and {len(ids)} ids")
        ids_t = tuple(str(i) for i in ids)
        if len(set(ids_t)) != POOL_SIZE:
            raise InputError(f"initial pool: pair ids must be unique, got {ids_t}")
        cand = self._score(None, P_b, P_c)
        self._pool_ids, self._P_base, self._P_cam = list(ids_t), P_b.copy(), P_c.copy()
        self._seen.update(ids_t)
        step = Algorithm1Step(
            k=0,
            pair_id=None,
            candidates=(cand,),
            accepted_slot=None,
            pool_ids=ids_t,
            fit=cand.fit,
            e_optimal=cand.e_icp,
            cost_optimal=cand.cost,
            reached=cand.cost <= self.e_required,
        )
        self._steps.append(step)
        return step

    def add(self, pair_id: str, p_base: ArrayLike, p_cam: ArrayLike) -> Algorithm1Step:
        """Lines 5-15: try the new pair in each slot, keep the best pool if it is better.

        Raises
        ------
        CalibrationError
            Before :meth:`start`, or once :attr:`done`.
        InputError
            A malformed pair or a pair id already used.
        """
        prev = self.last
        if self.done:
            why = "e_required reached" if prev.reached else f"k_max = {self.k_max} pairs taken"
            raise CalibrationError(f"Algorithm 1 has finished ({why}); start a new run")
        pid = str(pair_id)
        if pid in self._seen:
            raise InputError(f"pair {pid!r}: already given to this run")
        pb, pc = check_pairs(np.reshape(p_base, (1, 3)), np.reshape(p_cam, (1, 3)), min_pairs=1, determined=False)
        self._seen.add(pid)
        candidates = []
        for slot in range(POOL_SIZE):
            P_b = self._P_base.copy()
            P_c = self._P_cam.copy()
            P_b[slot], P_c[slot] = pb[0], pc[0]
            candidates.append(self._score(slot, P_b, P_c))
        best = min(candidates, key=lambda c: c.cost)
        accepted = best.cost < prev.cost_optimal
        if accepted and best.slot is not None:
            self._P_base[best.slot], self._P_cam[best.slot] = pb[0], pc[0]
            self._pool_ids[best.slot] = pid
            fit, e, cost = best.fit, best.e_icp, best.cost
        else:
            fit, e, cost = prev.fit, prev.e_optimal, prev.cost_optimal
        step = Algorithm1Step(
            k=prev.k + 1,
            pair_id=pid,
            candidates=tuple(candidates),
            accepted_slot=best.slot if accepted else None,
            pool_ids=tuple(self._pool_ids),
            fit=fit,
            e_optimal=e,
            cost_optimal=cost,
            reached=cost <= self.e_required,
        )
        self._steps.append(step)
        return step


def run_algorithm1(
    ids: Sequence[str],
    P_base: ArrayLike,
    P_cam: ArrayLike,
    evaluate: Evaluate,
    cost: Cost = translation_cost,
    *,
    e_required: float,
    k_max: int | None = None,
    with_scale: bool = False,
) -> Algorithm1Result:
    """Batch Algorithm 1 over pairs in their given order.

    The first four pairs form the initial pool; the others come one per step
    until the cost reaches ``e_required``, ``k_max`` pairs were taken
    (default: all of them) or the pairs run out.
    """
    P_b, P_c = check_pairs(P_base, P_cam)
    if len(ids) != len(P_b):
        raise InputError(f"ids: expected {len(P_b)} pair ids, got {len(ids)}")
    n_new = len(P_b) - POOL_SIZE
    alg = Algorithm1(evaluate, cost, e_required=e_required, k_max=n_new if k_max is None else k_max, with_scale=with_scale)
    alg.start(list(ids[:POOL_SIZE]), P_b[:POOL_SIZE], P_c[:POOL_SIZE])
    i = POOL_SIZE
    while not alg.done and i < len(P_b):
        alg.add(ids[i], P_b[i], P_c[i])
        i += 1
    return alg.result()
