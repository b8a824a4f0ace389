"""The array's digital twin: the membrane model plus its current state.

:class:`ArrayTwin` is what users, the ROS node, replay and studies talk to.  Each unit
is ``driven`` (its indenter position imposed: the paper's characterisation rig),
``free`` (no indenter) or ``biased`` (its indenter rides on a bias element: an actuator
unit, section 2 of the paper).  Give it per-unit displacements [m] (driven units),
voltages [V] and external forces [N] (biased units); :meth:`ArrayTwin.solve` returns
the quasi-static equilibrium, :meth:`ArrayTwin.step` advances biased units with a
moving mass by one time step (:mod:`.dynamics`).  Both give a :class:`TwinResult` with
per-unit position, velocity, force [N] and capacitance [F].  The twin keeps the last
state and the tangent factorisation there, so a small change of command is a warm
update.

Unilateral contact (config ``contact``): an indenter can push the membrane but not pull
it.  When a solve needs a negative force from it, the disk is released (a homotopy of
its force to zero, :mod:`.actuator`) and the unit is free; a driven indenter stays at
its command, a biased one moves to where its bias and force balance (or, with mass,
flies).  When the membrane's centre comes down to the indenter, contact resumes.  The
contact is all or nothing over the flat disk.

Background tangents (``background_tangent=True``, what the node uses): a warm update
whose tangent, from an earlier state, is going stale (it needed three Newton iterations,
or a step left more than :data:`BACKGROUND_CONTRACTION` of the residual it began with) has the
tangent at its converged state computed and factored in a worker thread (the kernels
release the GIL), and a later update starts from it; meanwhile the solver keeps the stale
tangent while the iterations it needs cost less than a factorisation
(:attr:`.solver.EquilibriumSolver.refresh_elsewhere`).  So the updates of a smooth command
stream keep converging in one iteration, nearly all, without waiting for a factorisation
(5-10 ms on the default mesh, several update periods at 500 Hz).  The equilibria are the
same (Newton converges to the same tolerances with any tangent); only which tangent an
update starts from depends on timing.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .actuator import ActuatorLoad, UnitLoad, free_flight, rest_position
from .bias import NoBias
from .config import ArrayConfig
from .dynamics import NewmarkStep
from .kernels import solve_small
from .membrane import BIASED, DRIVEN, FREE, MembraneModel, held
from .snap import Snap
from .solver import (
    ConvergenceError,
    EquilibriumSolver,
    Factorisation,
    NewtonSettings,
    SolveCancelled,
    compile_continuation,
)

__all__ = ["ArrayTwin", "TwinResult", "ConvergenceError", "BIASED", "DRIVEN", "FREE", "SolveCancelled",
           "command_error"]

#: Contact switches (lift-off, release, touch-down) one solve may make before it gives up.
MAX_CONTACT_SWITCHES = 6
#: Times a dynamic step that fails to converge is split in halves.
MAX_SUBSTEP_LEVELS = 6


#: With ``background_tangent``, a warm update that took this many Newton iterations has the
#: tangent at its state computed in the worker thread.  Measured on the 1-by-3 default mesh,
#: a 1 Hz sine on every unit at 500 updates a second, each refresh ready four updates after
#: it started: 2 -> 1.86 iterations per update and 130 refreshes a second (0.8 of a core);
#: 3 -> 2.16 iterations and 47 a second; 4 -> 2.53 iterations (refactoring in the solver's
#: own thread again, 0.018 per update); no background tangents: 2.58 and 0.036.
BACKGROUND_ITERATIONS = 3
#: With ``background_tangent``, a warm update in which a Newton step on a tangent from an earlier
#: state left more than this fraction of the residual it began with (the tangent is going stale, though the update
#: may still converge in one iteration: :attr:`.solver.EquilibriumSolver.stale_contraction`) has
#: the tangent at its state computed in the worker thread too, before updates need a second
#: iteration.  Measured on the 1-by-3 default mesh, a 1 Hz sine on every unit at 500 updates a
#: second (the first step's ratio is 0.08 at the median of one-iteration updates, 0.35 of
#: two-iteration ones): 0.1 -> 0.2 % of the updates take two iterations (7 % with only the rule
#: above), 29 refreshes a second instead of 9 (0.15 of a core); the node at 500 Hz with
#: ``realtime_priority: 10`` held 99.3-99.8 % of its ticks instead of 97.5 %.
BACKGROUND_CONTRACTION = 0.1
#: Threads of a background tangent's factorisation: one.  It runs beside the updates, and a
#: second thread for it took the core the updates need (the node at 500 Hz, benchmarks/bench_core.py
#: --node with realtime_priority 10: 69.1 / 52.8 % of the ticks held with one, 35.2 / 47.4 % with two).
BACKGROUND_FACTOR_THREADS = 1


#: Nice increment of the worker thread of background tangents and checks (Linux): its work yields the
#: core to the updates.  Measured with the node at 500 Hz under normal scheduling (benchmarks/bench_core.py
#: --node 10, one round each, alternating): 96.3 / 96.7 % of the ticks held against 92.7 / 93.8 % at the
#: node's own nice (19: 96.8 / 97.5 %).  Under real-time scheduling (the node's ``realtime_priority``) a
#: thread's nice value does not count.
BACKGROUND_NICE = 10


def lower_thread_priority() -> None:
    """Raise the calling thread's nice value by :data:`BACKGROUND_NICE` (at most 19), on Linux only.

    Linux schedules threads one by one and lets any thread lower its own priority; elsewhere
    ``setpriority`` on a thread id would renice the whole process, so nothing is done.  A refusal (a
    sandbox without the system call) leaves the thread as it was: it costs speed, never a result.
    """
    if not sys.platform.startswith("linux"):
        return
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + BACKGROUND_NICE))
    except OSError:
        return


def verdict_of(job: Future, judge: Callable[[object], bool | None]) -> Future:
    """A future of ``judge(result of job)``, set by the thread that finishes ``job`` (its exception passed on):
    a stability check's verdict from a tangent computed in a worker thread."""
    verdict: Future = Future()

    def judged(done: Future) -> None:
        if done.exception() is not None:
            verdict.set_exception(done.exception())
        else:
            verdict.set_result(judge(done.result()))

    job.add_done_callback(judged)
    return verdict


@dataclass(frozen=True)
class TwinResult:
    """One equilibrium of the array and everything known about it (SI units).

    Attributes
    ----------
    displacement : ndarray
        Position of each unit [m]: its indenter's height (the command of a driven
        unit, ``w`` of a biased one, also when lifted off) or, for a free unit, its
        centre deflection.  Also :attr:`position`.
    voltage : ndarray
        Voltage per unit [V].
    modes : tuple of str
        ``"driven"``, ``"free"`` or ``"biased"`` per unit.
    force : ndarray
        Axial force on each indenter [N], eq. 10; positive when the membrane pulls
        the indenter back towards the plane; 0 for free and lifted-off units.  At a
        biased unit's equilibrium it equals ``bias_force + external_force``.
    capacitance : ndarray
        Capacitance of each unit [F], eq. 7, whole electrode.
    delta_capacitance : ndarray
        ``capacitance`` minus the flat pre-stretched 0 V value [F].
    centre_deflection : ndarray
        Out-of-plane position of each unit centre [m].
    peak_field : ndarray
        Largest true electric field ``V / (t0 l3)`` on each electrode [V/m].
    velocity : ndarray
        ``dw/dt`` of each unit [m/s] after a :meth:`ArrayTwin.step` (Newmark velocity of
        a biased indenter with mass, the position's difference quotient otherwise); 0
        after a quasi-static solve.
    bias_force : ndarray
        ``B_k(w_k)`` of each biased unit's bias element [N]; 0 for other units.
    external_force : ndarray
        Commanded external force ``f_k`` on each biased indenter [N]; 0 for other units.
    lifted_off : ndarray of bool
        Per unit, whether its indenter (with ``contact``) has lost the membrane.
    snaps : tuple of Snap
        Snap-throughs on the way to this state (quasi-static solves):
        which unit, from where to where (:mod:`.snap`).
    positions : ndarray, shape (n_nodes, 3)
        Deformed node positions [m].
    energy : float
        Stored energy of the membrane [J].
    min_principal_stress : float
        Smallest in-plane principal Cauchy stress outside held indenter disks [Pa].
    wrinkled : bool
        ``min_principal_stress < 0``: a compressed region, which a real membrane
        relieves by wrinkling and this model does not represent.
    field_exceeded : bool
        Some ``peak_field`` is above the configured ``breakdown_field``.
    stable : bool or None
        The tangent at the state is positive definite (a stable minimum; for biased
        units with their bias stiffness ``-dB/dw``, without inertia); ``None`` if not
        checked.
    iterations, factorisations, step_cuts : int
        Newton iterations, tangent factorisations and load-step halvings of the solve.
    residual : float
        Largest free residual force at convergence [N].
    solve_time : float
        Wall time of the solve [s].
    """

    displacement: np.ndarray
    voltage: np.ndarray
    modes: tuple
    force: np.ndarray
    capacitance: np.ndarray
    delta_capacitance: np.ndarray
    centre_deflection: np.ndarray
    peak_field: np.ndarray
    velocity: np.ndarray
    bias_force: np.ndarray
    external_force: np.ndarray
    lifted_off: np.ndarray
    snaps: tuple
    positions: np.ndarray
    energy: float
    min_principal_stress: float
    wrinkled: bool
    field_exceeded: bool
    stable: bool | None
    iterations: int
    factorisations: int
    step_cuts: int
    residual: float
    solve_time: float

    @property
    def position(self) -> np.ndarray:
        """Position of each unit [m]: indenter height (driven, biased) or centre deflection (free)."""
        return self.displacement

    @property
    def snapped(self) -> np.ndarray:
        """Per unit, whether it snapped through on the way to this state."""
        out = np.zeros(len(self.modes), dtype=bool)
        out[[snap.unit for snap in self.snaps]] = True
        return out

    @property
    def events(self) -> list[str]:
        """Human-readable snap-throughs and lift-offs (physical events, not model faults)."""
        lifted = [f"unit {k + 1}: indenter lifted off the membrane" for k in np.flatnonzero(self.lifted_off)]
        return [snap.describe() for snap in self.snaps] + lifted

    @property
    def flags(self) -> tuple[str, ...]:
        """Which of ``"unstable"``, ``"wrinkled"``, ``"field_exceeded"`` apply (for counting)."""
        return tuple(name for name, on in (("unstable", self.stable is False), ("wrinkled", self.wrinkled),
                                           ("field_exceeded", self.field_exceeded)) if on)

    @property
    def warnings(self) -> list[str]:
        """Human-readable list of what is wrong with this state (empty if nothing), one per flag."""
        text = {"unstable": "equilibrium is not a stable minimum (tangent not positive definite)",
                "wrinkled": f"compressive principal stress {self.min_principal_stress:.4g} Pa: membrane would wrinkle",
                "field_exceeded": f"electric field {self.peak_field.max() / 1e6:.4g} V/um exceeds the breakdown limit"}
        return [text[name] for name in self.flags]

    @property
    def ok(self) -> bool:
        """True when no warning applies."""
        return not self.warnings


def command_error(kind: str, values: Sequence[float], cfg: ArrayConfig) -> str | None:
    """Why a command the node or a replay would reject is invalid, or None.

    ``kind`` is "displacement", "voltage" or "force".  Stricter than
    :meth:`ArrayTwin.solve` (which solves any finite command within
    ``max_displacement``): a voltage must also be >= 0 and keep the flat
    pre-stretched field below ``breakdown_field``.  A force [N] may take any finite value."""
    n = cfg.n_units
    if len(values) != n:
        return f"{kind} command has {len(values)} values, expected {n} (one per unit)"
    # Plain Python on a few values: the node checks every command (500 a second) in its executor.
    arr = [float(v) for v in values]
    if not all(math.isfinite(v) for v in arr):
        return f"{kind} command contains NaN or inf: {arr}"
    if kind == "force":
        return None
    if kind == "displacement":
        limit = cfg.scaled("max_displacement")
        if any(abs(v) > limit for v in arr):
            return f"displacement {arr} m beyond max_displacement {limit} m"
        return None
    if any(v < 0 for v in arr):
        return f"negative voltage {arr} V (the electrodes are driven by one polarity)"
    v_max = cfg.hv_voltage(cfg.breakdown_field)
    if any(v > v_max for v in arr):
        return (f"voltage {arr} V above {v_max:.0f} V, where the flat pre-stretched field "
                f"reaches breakdown_field {cfg.breakdown_field:.4g} V/m")
    return None



class ArrayTwin:
    """A live twin of the array described by ``config``.

    Parameters
    ----------
    config : ArrayConfig, optional
        The array; the paper's 1-by-3 default if omitted.  Its ``unit_modes``,
        ``bias``, ``mass``, ``damping`` and ``contact`` describe the units.
    settings : NewtonSettings, optional
        Solver tolerances.
    background_tangent : bool
        Refresh the tangent of warm updates in a worker thread (see the module
        docstring); driven and free units only (with a biased unit every tangent is
        computed in the calling thread).  :meth:`close` stops the thread.

    Attributes
    ----------
    tangents : Counter
        Background tangents ``"installed"`` (a later update started from them),
        ``"dropped"`` (by then the solver had factored a newer tangent itself, or a solve
        had failed) and ``"failed"`` (the factorisation raised; the solver's tangent kept).
        One under way at :meth:`reset` is never used (nor counted).

    Examples
    --------
    >>> twin = ArrayTwin()
    >>> res = twin.solve(displacement=[0, 0.015, 0], modes=["free", "driven", "free"])
    >>> res.force[1] > 0
    True
    """

    def __init__(self, config: ArrayConfig | None = None, settings: NewtonSettings | None = None,
                 background_tangent: bool = False):
        self.config = config or ArrayConfig()
        self.model = MembraneModel(self.config)
        self.solver = EquilibriumSolver(self.model, settings)
        self._pool = (ThreadPoolExecutor(1, thread_name_prefix="fe-tangent", initializer=lower_thread_priority)
                      if background_tangent else None)
        self.tangents: Counter = Counter()
        self.reset()

    def close(self) -> None:
        """Stop the background tangent thread (if any; waits for a factorisation under way)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)

    def warm_up(self) -> None:
        """Compile the solver's numba kernels now, or load them from numba's on-disk cache.

        The first solve of a process compiles them otherwise: ~10 s on the first run after
        an install, ~0.3 s later.  A live twin calls this before its first update.  It
        makes one checked solve with every unit driven to 1 mm at 0 V and one of the small dense
        systems of biased units' heights, compiles the continuation's algebra, then :meth:`reset`:
        the twin is left as a new one.
        """
        n = self.n_units
        self.solve(np.full(n, min(1e-3, 0.1 * self.config.scaled("max_displacement"))), np.zeros(n),
                   modes=(DRIVEN,) * n, check_stability=True, force=np.zeros(n))
        solve_small(np.eye(1), np.ones(1))
        compile_continuation()
        self.reset()

    @property
    def n_units(self) -> int:
        """Number of units."""
        return self.model.n_units

    def reset(self) -> None:
        """Return to the flat pre-stretched state at 0 V and 0 N, every indenter held at 0 m.

        The next call uses the config's ``unit_modes`` unless given others; a biased
        unit is then released from 0 m onto its bias."""
        n = self.n_units
        self._x = self.model.flat_state()
        self._held: tuple[str, ...] = (DRIVEN,) * n  # how the stored state holds each unit (lifted: free)
        self._modes: tuple[str, ...] = self.config.modes  # the commanded modes, default of the next call
        self._voltage = np.zeros(n)
        self._force = np.zeros(n)  # commanded external force on biased indenters [N]
        self._height = np.zeros(n)  # indenter height (driven: command, biased: w), free: centre [m]
        self._velocity = np.zeros(n)
        self._acceleration = np.zeros(n)
        self._lifted = np.zeros(n, dtype=bool)
        self._membrane_force = np.zeros(n)
        self.solver.factorisation = None
        self._pending: Future | None = None  # a background tangent from before the reset is dropped
        self._pending_over: Factorisation | None = None  # the tangent it is to replace
        self.last: TwinResult | None = None

    @property
    def acceleration(self) -> np.ndarray:
        """``d2w/dt2`` of each biased indenter with mass after the last :meth:`step` [m/s^2] (else 0)."""
        return self._acceleration.copy()

    def adopt(self, result: TwinResult, acceleration: Sequence[float] | None = None) -> None:
        """Continue from ``result``, a state of this array from another model (the reduced twin's, whose FE
        fallback of a time step starts where the reduced model left off).

        Positions, commands, modes, heights, velocities, lift-offs and ``acceleration``
        [m/s^2] (default 0) become the twin's state; the next solve or step starts from it
        with a fresh tangent."""
        self._x = np.asarray(result.positions, dtype=float).ravel().copy()
        self._lifted = np.asarray(result.lifted_off, dtype=bool).copy()
        self._modes = self.model.check_modes(result.modes)
        self._held = tuple(FREE if self._lifted[k] else m for k, m in enumerate(self._modes))
        self._voltage = np.array(result.voltage, dtype=float)
        self._force = np.array(result.external_force, dtype=float)
        self._height = np.array(result.displacement, dtype=float)
        self._velocity = np.array(result.velocity, dtype=float)
        self._acceleration = np.zeros(self.n_units) if acceleration is None else np.array(acceleration, dtype=float)
        self._membrane_force = np.array(result.force, dtype=float)
        self.solver.factorisation = None
        self._pending = None  # a background tangent under way is of another state
        self.last = result

    def _vector(self, name: str, values: Sequence[float] | float | None, default: np.ndarray) -> np.ndarray:
        if values is None:
            return default.copy()
        arr = np.asarray(values, dtype=float)
        if arr.ndim == 0:  # one value for every unit
            arr = np.full(self.n_units, float(arr))
        if arr.shape != (self.n_units,):
            raise ValueError(f"{name} must have one value per unit ({self.n_units}), got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite, got {arr.tolist()}")
        return arr

    def _commands(self, displacement, voltage, force, modes) -> tuple:
        """Commands with the previous ones as defaults, checked."""
        d1 = self._vector("displacement", displacement, self._height)
        v1 = self._vector("voltage", voltage, self._voltage)
        f1 = self._vector("force", force, self._force)
        modes = self.model.check_modes(modes if modes is not None else self._modes)
        limit = self.config.scaled("max_displacement")
        driven = np.array(modes) == DRIVEN
        if np.any(np.abs(d1[driven]) > limit):
            raise ValueError(f"displacement {d1.tolist()} m exceeds max_displacement ({limit} m)")
        return d1, v1, f1, modes

    def solve(self, displacement: Sequence[float] | float | None = None,
              voltage: Sequence[float] | float | None = None,
              modes: Sequence[str] | None = None, check_stability: bool | None = None,
              cancel: Callable[[], bool] | None = None, force: Sequence[float] | float | None = None) -> TwinResult:
        """Move the twin to a new command and return the quasi-static equilibrium there.

        The commands change linearly from the previous ones (a quasi-static path):
        biased units follow their equilibrium branch, and one that passes a limit
        point snaps through to the stable branch it jumps to (``result.snaps``).

        Parameters
        ----------
        displacement : sequence of float, optional
            Indenter displacement d_k per driven unit [m] (ignored for other units);
            default: the previous command.
        voltage : sequence of float or float, optional
            Voltage per unit [V]; default: the previous one.
        modes : sequence of str, optional
            ``"driven"``, ``"free"`` or ``"biased"`` per unit; default: the previous
            modes (the config's ``unit_modes`` after :meth:`reset`).
        check_stability : bool, optional
            Factor the tangent at the new state and report whether it is a stable
            minimum (``result.stable``); default: the solver setting.  Costs one
            factorisation (about 7 ms on the default mesh); without it
            ``result.stable`` is None.
        cancel : callable, optional
            Asked with no arguments before every Newton iteration; when it returns
            True the solve is abandoned (e.g. past a time budget, or for a newer
            request).  Called from the thread that runs the solve.
        force : sequence of float or float, optional
            External force f_k on each biased indenter towards +z [N] (ignored for
            other units); default: the previous one (0 after :meth:`reset`).

        Raises
        ------
        ConvergenceError
            If no equilibrium is found; the twin keeps its previous state.
        SolveCancelled
            ``cancel()`` returned True; the twin keeps its previous state (positions,
            command, modes, and the tangent it held).
        ValueError
            For a command of the wrong length or with NaN/inf.
        """
        tic = time.perf_counter()
        d1, v1, f1, modes = self._commands(displacement, voltage, force, modes)
        return self._advance(d1, v1, f1, modes, check_stability, None, tic, cancel)

    def step(self, dt: float, displacement: Sequence[float] | float | None = None,
             voltage: Sequence[float] | float | None = None, force: Sequence[float] | float | None = None,
             modes: Sequence[str] | None = None, check_stability: bool | None = None,
             cancel: Callable[[], bool] | None = None) -> TwinResult:
        """Advance the dynamics by ``dt`` [s] with the commands held at their new values.

        Biased units with ``mass > 0`` move by ``m w'' + c w' = B(w) + f - F(w, V)``
        (Newmark average acceleration, one Newton solve per step, :mod:`.dynamics`);
        the membrane and massless units are quasi-static.  A step that fails to
        converge is split in halves (up to 6 times).  Arguments as :meth:`solve`.
        """
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite time step > 0 s, got {dt}")
        tic = time.perf_counter()
        d1, v1, f1, modes = self._commands(displacement, voltage, force, modes)
        return self._substeps(dt, d1, v1, f1, modes, check_stability, tic, 0, cancel)

    def _substeps(self, dt: float, d1, v1, f1, modes, check, tic: float, level: int, cancel) -> TwinResult:
        try:
            return self._advance(d1, v1, f1, modes, check, dt, tic, cancel)
        except ConvergenceError:
            if level >= MAX_SUBSTEP_LEVELS:
                raise
            self._substeps(0.5 * dt, d1, v1, f1, modes, check, tic, level + 1, cancel)
            return self._substeps(0.5 * dt, d1, v1, f1, modes, check, tic, level + 1, cancel)

    # ------------------------------------------------------------------ one update
    def _advance(self, d1: np.ndarray, v1: np.ndarray, f1: np.ndarray, modes: tuple[str, ...],
                 check: bool | None, dt: float | None, tic: float, cancel=None) -> TwinResult:
        """Solve (``dt`` None) or step to the commands; commit the state only when it succeeded.

        After a failure (:class:`ConvergenceError`, :class:`SolveCancelled`) the solver's
        tangent may be one of a state on the way, not of the state kept: the solver gets back
        the one it started from (a node that abandons solves past their budget would otherwise
        pay a factorisation at the start of the next one, ~5-10 ms, which makes it overrun
        again)."""
        self._collect_tangent()
        start_tangent = self.solver.factorisation
        self.solver.refresh_elsewhere = self._pool is not None and BIASED not in modes
        self.solver.stale_contraction = 0.0
        try:
            result = self._attempt(d1, v1, f1, modes, check, dt, tic, cancel)
        except (ConvergenceError, SolveCancelled):
            self.solver.factorisation = start_tangent
            raise
        if (self.solver.refresh_elsewhere and self._pending is None and result.factorisations == 0
                and (result.iterations >= BACKGROUND_ITERATIONS
                     or self.solver.stale_contraction > BACKGROUND_CONTRACTION)
                and BIASED not in self._held):
            self._pending, self._pending_over = self._tangent_job(), self.solver.factorisation
        return result

    def _tangent_job(self) -> Future:
        """The tangent at the current state factored in the worker thread, with the disks' influence vectors."""
        return self._pool.submit(self.solver.background_tangent, self._x, self.model.maxwell(self._voltage),
                                 self._held, self.solver.disk_groups(self._held), BACKGROUND_FACTOR_THREADS)

    def check_in_background(self) -> Future | None:
        """Check whether the current state is a stable minimum in the worker thread (``background_tangent``).

        The tangent at the state is computed and factored there, where a checked :meth:`solve`
        does it in the calling thread (~7 ms on the default mesh: three update periods at
        500 Hz); the returned future's result is the verdict of ``TwinResult.stable`` (None if
        the factorisation gives no inertia).  If no background tangent is under way, a later
        update starts from this one, as from any (:attr:`tangents`).

        Returns None when the twin has no worker thread, no state yet, or holds a biased unit
        (its check needs the bordered tangent: a checked :meth:`solve`).
        """
        if self._pool is None or self.last is None or BIASED in self._held:
            return None
        job = self._tangent_job()
        if self._pending is None:
            self._pending, self._pending_over = job, self.solver.factorisation
        return verdict_of(job, lambda fact: None if fact.negative_pivots < 0 else fact.negative_pivots == 0)

    def _collect_tangent(self) -> None:
        """Start from a finished background tangent if the solver still has the one it was to replace."""
        if self._pending is None or not self._pending.done():
            return
        pending, self._pending = self._pending, None
        if pending.exception() is not None:
            self.tangents["failed"] += 1
            return
        if self.solver.factorisation is not self._pending_over:  # refactored since, or a failure, other modes
            self.tangents["dropped"] += 1
            return
        self.solver.factorisation = pending.result()
        self.tangents["installed"] += 1

    def _attempt(self, d1: np.ndarray, v1: np.ndarray, f1: np.ndarray, modes: tuple[str, ...],
                 check: bool | None, dt: float | None, tic: float, cancel) -> TwinResult:
        """One update with its contact switches (see :meth:`_advance`)."""
        cfg, model, n = self.config, self.model, self.n_units
        laws, mass = cfg.per_unit("bias"), cfg.per_unit("mass")
        contact = np.array([c and held(m) for c, m in zip(cfg.per_unit("contact"), modes)])
        newmark = {}
        if dt is not None:
            damping = cfg.per_unit("damping")
            state = zip(self._height, self._velocity, self._acceleration)
            newmark = {k: NewmarkStep(mass[k], damping[k], dt, w, v, a)
                       for k, (w, v, a) in enumerate(state) if modes[k] == BIASED and mass[k] > 0}
        lifted = self._lifted & contact
        releasing = np.zeros(n, dtype=bool)
        x, held_as, v0, f0 = self._x, self._held, self._voltage, self._force
        heights, forces = self._height.copy(), self._membrane_force
        snaps: list[Snap] = []
        tolerance = self.solver.settings.residual_tol * model.force_scale
        for _ in range(MAX_CONTACT_SWITCHES + 1):
            as_solved = tuple(BIASED if releasing[k] else FREE if lifted[k] else modes[k] for k in range(n))
            x_start = x.copy()
            centre = x_start.reshape(-1, 3)[model.mesh.centre_nodes, 2]
            d0 = np.where(np.array(held_as) == DRIVEN, heights, centre)
            loads = {}
            for k in np.flatnonzero(np.array(as_solved) == BIASED):
                if releasing[k]:  # its indenter lets go: the disk's force goes to 0
                    loads[k] = UnitLoad(NoBias(), 0.0, 0.0, held_force=forces[k])
                elif held_as[k] == BIASED:
                    loads[k] = UnitLoad(laws[k], f0[k], f1[k], newmark=newmark.get(k))
                else:  # placed on its bias now: from where the indenter is
                    model.place_disk(x_start, k, heights[k] if k in newmark else centre[k])
                    start = forces[k] if held_as[k] == DRIVEN else 0.0
                    loads[k] = UnitLoad(laws[k], f1[k], f1[k], held_force=None if k in newmark else start,
                                        newmark=newmark.get(k))
            detect = dt is None or any(m == BIASED and k not in newmark for k, m in enumerate(as_solved))
            # Newmark units start at the constant-acceleration prediction w + dt v + dt^2 a / 2.
            guess = {k: step.w + dt * step.v + 0.5 * dt**2 * step.a for k, step in newmark.items()
                     if as_solved[k] == BIASED and held_as[k] == BIASED}
            x_new, r, point, stats = self.solver.solve(x_start, as_solved, d0, d1, v0, v1, check,
                                                       ActuatorLoad(loads) if loads else None, detect, guess,
                                                       cancel)
            snaps += stats.snaps
            out = model.outputs(x_new, r, point, v1, as_solved)
            heights = np.where(np.array(as_solved) == DRIVEN, d1, out.centre_deflection)
            for k in np.flatnonzero(lifted & (np.array(modes) == DRIVEN)):
                heights[k] = d1[k]
            switched = False
            for k in np.flatnonzero(contact):
                if releasing[k]:  # released: free from now on
                    releasing[k], lifted[k], switched = False, True, True
                elif not lifted[k] and out.force[k] < -tolerance:
                    releasing[k], switched = True, True
                elif lifted[k]:
                    indenter = self._indenter(k, modes[k], laws[k], f1[k], d1[k], self._height[k],
                                              out.centre_deflection[k], newmark.get(k), dt)
                    if indenter is None or out.centre_deflection[k] < indenter:
                        lifted[k], switched = False, True
                    else:
                        heights[k] = indenter
            if not switched:
                break
            x, held_as, v0, f0, forces = x_new, as_solved, v1, f1, out.force
        else:
            raise ConvergenceError(f"the contact of units {[k + 1 for k in np.flatnonzero(contact)]} did not "
                                   f"settle after {MAX_CONTACT_SWITCHES} switches between lift-off and touch-down")
        return self._commit(x_new, as_solved, modes, heights, v1, f1, out, point, stats, lifted, snaps, newmark,
                            dt, tic)

    def _indenter(self, k: int, mode: str, law, force: float, command: float, previous: float, membrane: float,
                  newmark: NewmarkStep | None, dt: float | None) -> float | None:
        """Height [m] of the lifted-off indenter of unit ``k``, or None if it is back on the membrane."""
        if mode == DRIVEN:
            return command
        cfg, model = self.config, self.model
        try:
            if newmark is not None:
                return free_flight(UnitLoad(law, force, force, newmark=newmark),
                                   self.solver.settings.increment_tol * model.length_scale)
            return rest_position(law, force, previous, membrane, cfg.scaled("max_displacement"),
                                 self.solver.settings.snap_march * model.length_scale)
        except ValueError as exc:
            raise ConvergenceError(f"unit {k + 1}: {exc}") from None

    def _commit(self, x, as_solved, modes, heights, v1, f1, out, point, stats, lifted, snaps, newmark, dt,
                tic) -> TwinResult:
        """Store the new state and return it as a :class:`TwinResult`."""
        cfg, model, n = self.config, self.model, self.n_units
        laws = cfg.per_unit("bias")
        biased = np.array(modes) == BIASED
        velocity, acceleration = np.zeros(n), np.zeros(n)
        if dt is not None:
            velocity = (heights - self._height) / dt
            for k, step in newmark.items():
                velocity[k], acceleration[k] = step.velocity(heights[k]), step.acceleration(heights[k])
        self._x, self._held, self._modes = x, as_solved, modes
        self._voltage, self._force, self._height = v1, np.where(biased, f1, 0.0), heights
        self._velocity, self._acceleration, self._lifted = velocity, acceleration, lifted
        self._membrane_force = out.force
        stable = None
        if stats.stability_checked and stats.negative_eigenvalues >= 0:
            stable = stats.negative_eigenvalues == 0
        self.last = TwinResult(
            displacement=heights.copy(), voltage=v1, modes=modes, force=out.force,
            capacitance=out.capacitance, delta_capacitance=out.capacitance - model.flat_capacitance,
            centre_deflection=out.centre_deflection, peak_field=out.peak_field, velocity=velocity,
            bias_force=np.array([laws[k].force(heights[k]) if biased[k] else 0.0 for k in range(n)]),
            external_force=self._force.copy(), lifted_off=lifted.copy(), snaps=tuple(snaps),
            positions=x.reshape(-1, 3).copy(), energy=model.energy(point, v1),
            min_principal_stress=out.min_principal_stress, wrinkled=out.min_principal_stress < 0,
            field_exceeded=bool(np.any(out.peak_field > cfg.breakdown_field)), stable=stable,
            iterations=stats.iterations, factorisations=stats.factorisations, step_cuts=stats.step_cuts,
            residual=stats.residual_norm, solve_time=time.perf_counter() - tic)
        return self.last
