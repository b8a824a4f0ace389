"""Newmark average-acceleration integration of the biased indenters' motion.

Each biased unit with a moving mass ``m_k > 0`` obeys

    m_k w'' + c_k w' = B_k(w) + f_k - F_k(w, V),

the membrane being quasi-static (its own mass, ~0.15 g per unit, is small next to an
indenter and its bias element).  Newmark's method with ``beta = 1/4``, ``gamma = 1/2``
(the trapezoidal rule: unconditionally stable, second order, no numerical damping,
energy-conserving for linear systems) relates the new state to the new height
``w = w_{n+1}``:

    w* = w_n + dt v_n + (1/2 - beta) dt^2 a_n                      (predictor)
    a(w) = (w - w*) / (beta dt^2)
    v(w) = v_n + dt ((1 - gamma) a_n + gamma a(w)),

so a step is one equilibrium solve in which the indenter's generalised force is
``G(w) = B(w) + f - m a(w) - c v(w)``, with ``dG/dw = dB/dw - m / (beta dt^2) - c gamma /
(beta dt)``: the inertial stiffness ``m / (beta dt^2)`` joins the bordered tangent
(:mod:`.indenters`).  The period error of the scheme is ``(omega dt)^2 / 12`` (0.13% at
``dt = T / 50``).
"""

from __future__ import annotations

from dataclasses import dataclass

BETA, GAMMA = 0.25, 0.5


@dataclass(frozen=True)
class NewmarkStep:
    """One Newmark step of a unit from state ``(w, v, a)`` at time n over ``dt``.

    Attributes
    ----------
    mass, damping : float
        ``m`` [kg] (> 0) and ``c`` [N s/m].
    dt : float
        Time step [s].
    w, v, a : float
        Height [m], velocity [m/s] and acceleration [m/s^2] at time n.
    """

    mass: float
    damping: float
    dt: float
    w: float
    v: float
    a: float

    @property
    def predictor(self) -> float:
        """``w* = w_n + dt v_n + (1/2 - beta) dt^2 a_n`` [m]."""
        return self.w + self.dt * self.v + (0.5 - BETA) * self.dt**2 * self.a

    def acceleration(self, w: float) -> float:
        """``a(w) = (w - w*) / (beta dt^2)`` [m/s^2]."""
        return (w - self.predictor) / (BETA * self.dt**2)

    def velocity(self, w: float) -> float:
        """``v(w) = v_n + dt ((1 - gamma) a_n + gamma a(w))`` [m/s]."""
        return self.v + self.dt * ((1.0 - GAMMA) * self.a + GAMMA * self.acceleration(w))

    def inertial_force(self, w: float) -> tuple[float, float]:
        """``(m a(w) + c v(w), d/dw)``: ``d/dw = m / (beta dt^2) + c gamma / (beta dt)`` [N, N/m]."""
        force = self.mass * self.acceleration(w) + self.damping * self.velocity(w)
        stiffness = self.mass / (BETA * self.dt**2) + self.damping * GAMMA / (BETA * self.dt)
        return force, stiffness
