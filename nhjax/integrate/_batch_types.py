"""What a batch returns and raises: ``BatchTrajectory``, ``BatchError`` and the member
statuses that ``simulate_batch``, the impact batches and the Dask path share.

They live below all three (``_local_batch.py``, ``impacts.py``, ``distributed.py``)
so that each imports them without importing another batch path.
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.tree_util as jtu
import numpy as np

from ..errors import NhjaxError
from .simulate import Trajectory

__all__ = ["BatchError", "BatchTrajectory", "MemberStatuses", "STATUSES"]


class BatchError(NhjaxError, RuntimeError):
    """Some members of a batch failed. ``members``: indices; ``reasons``: per member;
    ``times``: time of failure per member (t0 for bad initial states);
    ``trajectory``: the batch result (None for bad initial states)."""

    def __init__(self, what, members, reasons, times, trajectory=None):
        self.members, self.reasons, self.times, self.trajectory = members, reasons, times, trajectory
        shown = "; ".join(
            f"member {m}: {r} at t = {t:.6g}" for m, r, t in list(zip(members, reasons, times))[:8]
        )
        more = f" (and {len(members) - 8} more)" if len(members) > 8 else ""
        super().__init__(f"{what} in {len(members)} member(s) of the batch: {shown}{more}")


#: Member statuses of a batch (``BatchTrajectory.status``), in the order of their codes.
STATUSES = ("ok", "guard", "max_steps", "non-finite", "solver failure", "bad x0")
OK, GUARD, MAX_STEPS, NONFINITE, SOLVER, BAD_X0 = range(len(STATUSES))


class MemberStatuses:
    """What every batch result says about its members, from its ``status`` codes
    (indices into the class's ``STATUS_NAMES``) and ``reasons`` (member -> text for
    every member that did not end as it should): ``simulate_batch``'s ``BatchTrajectory``
    and the impact batches' ``ImpactBatchTrajectory`` share it.

    Masks over the members: ``ok`` (reached t1), ``stopped`` (ended early as asked:
    a chart guard with ``on_guard="stop"``, max_impacts with ``on_max_impacts="stop"``),
    ``failed`` (anything else, bad inputs included)."""

    STATUS_NAMES: ClassVar[tuple] = ()
    OK_CODE: ClassVar[int] = 0
    STOP_CODES: ClassVar[tuple] = ()

    def __len__(self):
        return int(np.shape(self.status)[0])

    @property
    def ok(self):
        return np.asarray(self.status) == self.OK_CODE

    @property
    def stopped(self):
        return np.isin(np.asarray(self.status), self.STOP_CODES)

    @property
    def failed(self):
        return ~(self.ok | self.stopped)

    def status_names(self):
        """Each member's status as text."""
        return [self.STATUS_NAMES[int(s)] for s in np.asarray(self.status)]

    def counts(self) -> dict:
        """Number of members per status (statuses that occur)."""
        codes, n = np.unique(np.asarray(self.status), return_counts=True)
        return {self.STATUS_NAMES[int(c)]: int(k) for c, k in zip(codes, n)}

    def _reason_lines(self, show: int) -> list:
        bad = sorted(self.reasons)
        t = np.asarray(self.t_final)
        lines = [f"  member {m}: {self.reasons[m]} at t = {float(t[m]):.6g}" for m in bad[:show]]
        if len(bad) > show:
            lines.append(f"  ... and {len(bad) - show} more (traj.reasons)")
        return lines


class BatchTrajectory(MemberStatuses, Trajectory):
    """The result of ``simulate_batch``: every field of ``Trajectory`` with a leading
    member axis (``xs[i]`` is member i's saved states), plus per-member statuses.

    status : int array [B], codes into ``STATUSES``: "ok" (reached t1), "guard" (a chart
        guard stopped it at ``t_final``), "max_steps", "non-finite"
        (NaN/inf in the state), "solver failure" (e.g. the minimal step size), "bad x0"
        (the initial state failed the checks and was not solved; ``reasons`` says why).
    reasons : member -> text, for every member that is not "ok".
    guard : names of the guards that stopped members ("" if none).

    Masks: ``ok`` (reached t1 without failure), ``stopped`` (by a guard), ``failed``
    (anything else); ``valid`` marks the saved points of each member that lie before its
    end and are finite. ``x_final`` is each member's last saved state ([B, n]);
    ``x_end`` its state at ``t_final``. For a histogram of final states:
    ``traj.x_final[traj.ok]``.
    """

    status: Any = None
    reasons: dict = eqx.field(static=True, default_factory=dict)

    STATUS_NAMES = STATUSES
    OK_CODE = OK
    STOP_CODES = (GUARD,)

    @property
    def valid(self):
        ts = np.asarray(self.ts)
        fin = np.ones(ts.shape, bool)
        for a in jtu.tree_leaves(self.xs):
            fin &= np.isfinite(np.asarray(a)).reshape(ts.shape + (-1,)).all(-1)
        return fin & (ts <= np.asarray(self.t_final)[:, None])

    @property
    def x_final(self):
        return jtu.tree_map(lambda a: a[:, -1], self.xs)

    def summary(self, show: int = 8) -> str:
        """How many members reached t1, which did not and why, and the spread of steps
        and of the accuracy diagnostics over the members that did."""
        B, ok = len(self), self.ok
        counts = self.counts()
        lines = [f"{B} members: " + ", ".join(f"{k} {v}" for k, v in counts.items())]
        acc = np.asarray(self.num_accepted_steps)
        if ok.any():
            a = acc[ok]
            lines.append(f"  steps (ok members): min {a.min()}, median {int(np.median(a))}, max {a.max()}; "
                         f"rejected {int(np.asarray(self.num_rejected_steps)[ok].sum())} in all")
        for label, d in (("constraint", self.constraint_drift), ("invariant", self.invariant_drift)):
            for k, v in d.items():
                v = np.asarray(v)[ok]
                if v.size:
                    lines.append(f"  {label} '{k}': max |change| over ok members {v.max():.2e} "
                                 f"(median {np.median(v):.2e})")
        return "\n".join(lines + self._reason_lines(show))
