"""What pushes a biased indenter: bias, commanded force, inertia; and an indenter off the membrane.

:class:`UnitLoad` is the generalised force ``G_k(w, t)`` [N] of one biased unit along a
solve's load path (``t`` from 0 to 1), :class:`ActuatorLoad` collects them for the
solver (:class:`~.indenters.IndenterLoad`).  Three cases:

* on its bias: ``G = B(w) + f(t)``, ``f`` the commanded external force moving linearly
  from its old to its new value;
* just placed on its bias (the unit was driven or free, or touches the membrane again):
  ``G = t (B(w) + f) + (1 - t) F_0``, which starts from the membrane force ``F_0`` that
  held the disk before, so the path starts in equilibrium (a homotopy; with ``B = 0,
  f = 0`` it releases a disk whose indenter lifts off);
* in a Newmark step (:mod:`.dynamics`): minus the inertial and damping forces
  ``m a(w) + c v(w)``.

A lifted-off indenter (unilateral contact) moves on its own: :func:`rest_position`
finds where its bias and force balance quasi-statically, :func:`free_flight` advances
it by one Newmark step.
"""

from __future__ import annotations

from dataclasses import dataclass

from scipy.optimize import brentq

from .bias import BiasLaw
from .dynamics import NewmarkStep


@dataclass(frozen=True)
class UnitLoad:
    """``G(w, t)`` of one biased unit.

    Attributes
    ----------
    law : BiasLaw
        Its bias element.
    force_start, force_end : float
        Commanded external force at the start and end of the path [N].
    held_force : float or None
        Membrane force [N] that held the disk at the start of a placement homotopy; None
        when the unit was already on its bias.
    newmark : NewmarkStep or None
        Inertial and damping terms of a dynamic step; None quasi-statically.
    """

    law: BiasLaw
    force_start: float
    force_end: float
    held_force: float | None = None
    newmark: NewmarkStep | None = None

    def __call__(self, w: float, t: float) -> tuple[float, float]:
        """``(G, dG/dw)`` [N, N/m] at height ``w`` and path fraction ``t``."""
        g = self.law.force(w) + self.force_start + t * (self.force_end - self.force_start)
        dg = self.law.slope(w)
        if self.held_force is not None:
            g, dg = t * g + (1.0 - t) * self.held_force, t * dg
        if self.newmark is not None:
            inertial, stiffness = self.newmark.inertial_force(w)
            g, dg = g - inertial, dg - stiffness
        return g, dg


class ActuatorLoad:
    """The :class:`~.indenters.IndenterLoad` of a solve: a :class:`UnitLoad` per biased unit."""

    def __init__(self, loads: dict[int, UnitLoad]):
        self.loads = loads

    def __call__(self, unit: int, w: float, t: float) -> tuple[float, float]:
        """``(G, dG/dw)`` of ``unit``."""
        return self.loads[unit](w, t)

    def static_slope(self, unit: int, w: float) -> float:
        """``dB/dw`` of ``unit``'s bias (what a placement homotopy converges to)."""
        return self.loads[unit].law.slope(w)


def rest_position(law: BiasLaw, force: float, start: float, ceiling: float, limit: float,
                  step: float) -> float | None:
    """Where a lifted-off indenter comes to rest: ``B(w) + f = 0`` [m], or None if it reaches the membrane.

    Starting at ``start`` the indenter moves the way ``B + f`` pushes it, in
    increments ``step`` until the sign changes (then Brent's method), the membrane at
    ``ceiling`` stops it (None: contact again) or ``|w|`` passes ``limit``.

    Raises
    ------
    ValueError
        No rest position within ``limit``: the indenter falls away from the membrane.
    """

    def net(w: float) -> float:
        return law.force(w) + force

    g0 = net(start)
    if g0 == 0.0:
        return start
    direction = 1.0 if g0 > 0 else -1.0
    w = start
    while True:
        nxt = w + direction * step
        if direction > 0 and nxt >= ceiling:
            return None if net(ceiling) >= 0.0 else brentq(net, w, ceiling, xtol=1e-12)
        if abs(nxt) > limit or not law.contains(nxt):
            raise ValueError(f"the lifted-off indenter finds no rest position: its bias plus force "
                             f"{g0:.4g} N pushes it {'up' if direction > 0 else 'down'} beyond {nxt:.4g} m")
        if net(nxt) * g0 <= 0.0:
            return brentq(net, min(w, nxt), max(w, nxt), xtol=1e-12)
        w = nxt


def free_flight(load: UnitLoad, tolerance: float) -> float:
    """Height [m] after one Newmark step of an indenter off the membrane: ``m a + c v = B + f``.

    Newton on ``G(w) = 0`` (``load.newmark`` set, no membrane force), from the predictor.
    """
    w = load.newmark.predictor
    for _ in range(50):
        g, dg = load(w, 1.0)
        w_next = w - g / dg
        if abs(w_next - w) <= tolerance:
            return w_next
        w = w_next
    raise ValueError(f"the lifted-off indenter's step did not converge (last change {abs(w_next - w):.3g} m)")
