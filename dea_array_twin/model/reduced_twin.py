"""A kHz twin: the hyper-reduced model of :mod:`.reduced`, checked and backed up by the FE.

:class:`ReducedTwin` answers :meth:`~ReducedTwin.solve` like
:class:`~.twin.ArrayTwin` (same arguments, a :class:`~.twin.TwinResult` with the same
fields) from a :class:`~.reduced.ReducedModel`.  One update from the last state
``(q0, p0)``, ``p = (d, m)`` the driven displacements and the Maxwell coefficients
``m_u = 0.5 eps (V_u/t0)^2``, to a new command ``p1``:

1. **Predictor** with the sensitivities of the last refreshed Hessian ``H``:
   ``q_pred = q0 - H_qq^-1 H_qp (p1 - p0)``.
2. **One evaluation** of the hyper-reduced gradient ``g = dE/d(q, d, m, w)`` at
   ``(q_pred, p1)`` (:func:`.rom_kernels.evaluate`) and a Newton correction
   ``dq = -H_qq^-1 g_q``.  The outputs are energy derivatives, corrected to first
   order for ``dq``: the force on indenter k is ``F_k = dE/dd_k + H_dq dq`` (the
   energy-consistent force, paper eq. 10 as the derivative of the reduced energy),
   the capacitance ``C_u = -(eps/t0^2) (dE/dm_u + H_mq dq)`` (eq. 7).
3. For a large correction (one that changes an output by more than ``second_step`` of
   its scale) a **second evaluation** at
   ``q_pred + dq``, with the inverse ``H_qq^-1`` corrected by one Broyden update from the
   secant pair of the two evaluations; a slowly contracting second step marks the
   Hessian for a refresh.
4. The Hessian (and the predictor sensitivities) is **refreshed** (:func:`.rom_kernels.hessian`,
   a few ms) after such a step, when the command has moved more than ``refresh_distance``
   of the envelope since the last refresh, and on cold starts (first solve, after a
   fallback), which run Newton to convergence from the nearest training snapshot or
   from the FE state projected on the basis (keeping a Hessian while the steps contract
   fast: :data:`SETTLE_CONTRACTION`).

**Error indicator**: the residual along the enrichment vectors ``W`` (next POD modes and
the linear responses to each input that the basis was not built from),
``g_w = dE/dw``, is the part of the equilibrium the basis cannot represent.  Solving the
enriched linear problem with ``H`` gives the change of the outputs had ``W`` been in the
basis,

    delta_o = (H_oq H_qq^-1 H_qw - H_ow) S^-1 g_w,     S = H_ww - H_wq H_qq^-1 H_qw,

and the indicator is the largest ``|delta F_k| / F_ref_k`` or ``|delta C_u| / C_u``, times the
ROM's ``indicator_scale`` (calibrated in training against the FE: the raw estimate has the
size of the error, not that of a bound, and fell short of it by up to 4 times on the 4-by-4).

**Fallback**: a command outside the trained envelope (or with other unit modes), an
indicator above ``tolerance``, or a reduced Newton that fails is answered by the FE twin
(``result.fallback`` says why; :attr:`ReducedTwin.fallbacks` counts them), and the
reduced state is resynchronised from the FE state.

**Biased units** (issue 11's actuator mode) on a ROM trained with them driven: the
indenter displacement ``d_k``, an input of the ROM, becomes the unknown height ``w_k``
of ``F_k(q(d), d) = G_k(w_k)``, ``G_k = B_k(w_k) + f_k`` (and ``- m a(w) - c v(w)`` in a
Newmark time step, :mod:`.dynamics`), solved by Newton on the heights with the
condensed stiffness ``K = H_dd - H_dq H_qq^-1 H_qd`` of the refreshed Hessian, each
iterate one reduced update (:meth:`ReducedTwin._balance`); a predictor from that
tangent puts the first iterate at the new equilibrium to first order, so that a
control-loop step costs one evaluation.  Heights outside the trained range, a limit
point (``K - dG/dw`` not positive definite: snap-through), an indenter with contact
that would pull, and heights that do not converge go to the FE.
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, fields
from typing import Callable, Sequence

import numpy as np

from .actuator import UnitLoad
from .bias import BiasRangeError
from .config import BIASED, DRIVEN, ArrayConfig
from .dynamics import NewmarkStep
from .point_team import PointTeam
from .reduced import ReducedModel, RomMismatchError, check_config
from .rom_build import held_elements
from .rom_kernels import classify, combine, evaluate, heights, hessian, point_maps, project, reduced_tangent, update
from .solver import ConvergenceError, NewtonSettings, SolveCancelled
from .twin import ArrayTwin, TwinResult, verdict_of

#: Why the FE answered an update (:attr:`ReducedTwin.fallbacks`' keys, as ``result.fallback`` starts).
FALLBACKS = ("envelope", "indicator", "newton", "snap", "contact")
#: Reduced updates (evaluations) one solve may spend on the heights of its biased units
#: before the FE answers it (a warm update takes one or two).
MAX_HEIGHT_ITERATIONS = 8
#: Storage type of the sampled points' maps ``A_p`` (:func:`.rom_kernels.point_maps`).  An update streams
#: them from memory once per evaluation (16 MB on the 4-by-4 at 150 modes in float64, more than a core's
#: cache) and is bound by that: in float32 the 4-by-4's update took half the time, and forces and
#: capacitances moved by ~1e-7 of their values (the maps' rounding, 6e-8), four orders below a ROM's
#: tolerance (docs/rom.md).  With float32 maps an update's products with them are float32 arithmetic
#: too (the stresses and the sums over points float64; :func:`.rom_kernels.update`): another 20 % off the
#: 4-by-4's update, the outputs moved by 2e-7 to 4e-7 and the energy by up to 1e-6.  Cold solves,
#: Hessians and :func:`.rom_kernels.evaluate` keep float64 products.
MAP_DTYPE = np.float32
#: Modified Newton in :meth:`ReducedTwin._settle` (cold starts, jumps): the Hessian of the last refresh is
#: kept for the next step when this step was at most this fraction of the one before, else refreshed
#: (the first two steps always are).  A refresh is a full Hessian, ~14 ms on the 200-mode 4-by-4, an
#: evaluation ~0.35 ms: cold solves there took 3.1 refreshes and 8.1 evaluations (46 ms median) instead
#: of 5.5 and 6.5 (88 ms), the same states to round-off.
SETTLE_CONTRACTION = 0.1
#: With ``background_refresh``: a command farther than this many ``refresh_distance`` from where the Hessian
#: was taken, in some input, while the worker has not delivered a newer one, refreshes it in the calling
#: thread.  A stale Hessian's Newton corrections understate the error they leave (``second_step`` takes
#: them for it): on the 200-mode 4-by-4, whose worker needed ~60-90 ms a Hessian per point, the updates were 0.35 %
#: off at the default ``second_step``, 0.096 % with this (and stalls of a per-point refresh instead).
STALE_LIMIT = 2.0
#: Columns of the reduced Hessian (``[1, d, q, w]``) from which the refreshes are BLAS products
#: (:func:`.rom_kernels.hessian`; with ``background_refresh`` only when told the BLAS has one
#: thread, ``blas=True``).  Measured: 1-by-3, 51
#: columns, 0.4 -> 0.3 ms, not worth the BLAS helper thread that then spins beside the process (a
#: library loop's CPU per update went from 0.05 to 0.14 ms); 4-by-4, 173 columns 30 -> 7.3 ms, 273
#: columns 57 -> 14 ms.
BLAS_COLUMNS = 128
#: The shortest command step (``sqrt(sum (dp / range)^2)`` over the inputs) after which an update corrects the
#: predictor's ``dq/dp`` by a secant update (:func:`.rom_kernels.update`), with the refresh in the calling
#: thread only: a shorter step's change of ``q`` is mostly its Newton correction's error, not a slope; and a
#: worker's Hessian is older than the state, so the one-step correction under-corrects and the secant would
#: learn that (the 4-by-4's worker mode: 0.285 % force error against 0.079 %).
SECANT_STEP = 1e-3
#: Updates sum the gradient along ``W`` (the indicator's) after their last evaluation, from the stresses the
#: first kept, while more than this share of the recent updates evaluated twice (a second evaluation then
#: does not read the enrichment's maps in vain), else with their first evaluation (one pass fewer): on the
#: 4-by-4 the second evaluations are 85 % of the updates with the refresh in a worker, 7 % in the calling
#: thread with the secant updates (calling thread, paced 1 kHz: median 0.48-0.50 -> 0.45-0.47 ms).
DEFER_SHARE = 0.4
#: Weight of the last update in the running share of updates that evaluated twice.
SECONDS_WEIGHT = 0.05
#: Point maps (sampled and enrichment, bytes) from which ``threads=None`` shares the updates' evaluations
#: with a helper thread on a second core (:class:`.point_team.PointTeam`): one core's memory bandwidth bounds
#: an evaluation whose maps do not fit its 2 MB L2 cache; below that a helper's wake-up costs about what it
#: saves.
TEAM_BYTES = 2 * 1024**2


def _recover(reference: np.ndarray, vectors: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Full positions (n_nodes, 3) [m] of reduced coefficients ``z`` over ``[lift, basis]``."""
    return combine(reference, vectors, z).reshape(-1, 3)


@dataclass(frozen=True, init=False)
class ReducedResult(TwinResult):
    """A :class:`~.twin.TwinResult` of the reduced twin, with what the FE check said.

    ``positions`` (the full field, recovered from the reduced coordinates) is computed
    on first access, so an update does not pay for it.

    Attributes
    ----------
    error_indicator : float
        Estimated largest relative output error (force over its full scale,
        capacitance over its value); NaN when the FE answered outside the envelope.
    fallback : str
        Empty when the reduced model answered; else why the FE did.
    """

    error_indicator: float
    fallback: str

    def __init__(self, *, error_indicator: float, fallback: str = "", recover=None, **values):
        self.__dict__.update(values, error_indicator=error_indicator, fallback=fallback, _recover=recover)

    @functools.cached_property
    def positions(self) -> np.ndarray:  # noqa: D102 (documented in TwinResult)
        return self._recover()


class _Tangent:
    """The reduced Hessian at one state and what an update derives from it (:func:`.rom_kernels.reduced_tangent`).

    ``outputs`` holds the outputs' sensitivities to the inputs ``p = (d, m)`` with ``q`` kept at
    the reduced equilibrium, ``dO/dp = dO/dp|_q + dO/dq dq/dp``; its driven block is the
    condensed stiffness of the indenters,

        K = dF/dd = H_dd - H_dq H_qq^-1 H_qd,

    and ``centre`` the centre deflections' sensitivities to ``d``.
    """

    def __init__(self, twin: "ReducedTwin", hz: np.ndarray, hm: np.ndarray):
        self.stable, self.arrays = reduced_tangent(hz, hm, twin._nd, twin.rom.n_modes, twin._cap_factor,
                                                   twin._output_scale)
        self.hqq_inv = self.arrays[1]
        nd, sensitivity, out_q = twin._nd, self.arrays[0], self.arrays[2]
        direct = np.zeros(out_q.shape[:1] + sensitivity.shape[1:])  # dO/dp at fixed q: F = dE/dd, C ~ -dE/dm
        direct[:nd, :nd] = hz[1:1 + nd, 1:1 + nd]
        direct[:nd, nd:] = hm[1:1 + nd]
        direct[nd:, :nd] = -twin._cap_factor * hm[1:1 + nd].T
        self.outputs = direct + out_q @ sensitivity
        self.centre = twin._centre[:, 1:1 + nd] + twin._centre[:, 1 + nd:] @ sensitivity[:, :nd]


class _Refused(Exception):
    """The reduced model cannot answer this update: the FE does (``kind`` counts it, the message says why)."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind = kind


def _positive_definite(a: np.ndarray) -> bool:
    """Whether the small symmetric matrix ``a`` is positive definite."""
    if a.shape[0] == 1:
        return bool(a[0, 0] > 0.0)
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        return False
    return True


class ReducedTwin:
    """A twin answering from a trained :class:`~.reduced.ReducedModel`, with the FE as its fallback.

    Parameters
    ----------
    config : ArrayConfig
        The array; must be the one the ROM was trained on (else :class:`RomMismatchError`).
    rom : ReducedModel
        The trained model (e.g. read from a file by :func:`dea_array_twin.romfile.load_rom`).
    settings : NewtonSettings, optional
        Settings of the FE twin used for fallbacks.
    tolerance : float, optional
        Indicator level above which the FE answers (default: the ROM's training tolerance).
    fe : ArrayTwin, optional
        The FE twin to fall back on (default: a new one of ``config``).

    Attributes
    ----------
    second_step : float, optional
        A Newton correction that changes an output by more than this fraction of its
        scale (force reference, flat capacitance) gets a second evaluation; one whose
        second step still does, Newton to convergence.  Default: the tolerance, at most
        1e-3 (the error left after the first-order output correction is a fraction of
        the correction).
    refresh_distance : float
        Fraction of the envelope's range of any input (driven displacement, Maxwell
        coefficient) a command may move from the last Hessian refresh before the next
        update refreshes it.
    background_refresh : bool
        Compute refreshes of warm updates in a worker thread (the Hessian kernel
        releases the GIL) and use the newest finished one, so that no update waits for
        one (a real-time loop); cold starts and ``check_stability`` still refresh in
        the calling thread.  :meth:`close` stops the thread.
    threads : int, optional
        Threads that share an update's evaluations, the caller included: 1 evaluates in the
        calling thread alone; more start helper threads (:class:`.point_team.PointTeam`) that
        sleep between updates and claim chunks of points during them.  The outputs are the same
        to the bit either way.  Default: 2 when the point maps exceed :data:`TEAM_BYTES` and the
        process may run on two CPUs, else 1.  :meth:`close` stops the helpers.
    blas : bool, optional
        Whether a large ROM's (:data:`BLAS_COLUMNS`) Hessians are BLAS products, four
        times faster than summed point by point (:func:`.rom_kernels.hessian`).  Default:
        without ``background_refresh`` only: OpenBLAS's helper threads spin for ~0.1 s
        after a product, on the core beside a real-time twin's updates.  A process whose
        BLAS has one thread (:func:`dea_array_twin.blasthreads.single_threaded_blas`)
        passes True: its products run on the worker alone.

    Attributes
    ----------
    fallbacks : Counter
        Updates the FE answered, by reason (:data:`FALLBACKS`): ``"envelope"`` (also a biased height
        outside the trained range), ``"indicator"``, ``"newton"`` (also biased heights that do
        not converge), ``"snap"`` (a biased equilibrium at a limit point: ``K - dG/dw`` not
        positive definite) and ``"contact"`` (an indenter with unilateral contact that would
        pull, or is lifted off).
    team : PointTeam
        The threads sharing the updates' evaluations (``helped``: the chunks the helpers took).
    updates, evaluations, refreshes, resyncs : int
        Reduced updates answered, gradient evaluations, Hessian refreshes and restarts
        from an FE state (:meth:`request_resync`) so far.
    """

    def __init__(self, config: ArrayConfig | None, rom: ReducedModel, settings: NewtonSettings | None = None,
                 tolerance: float | None = None, fe: ArrayTwin | None = None, second_step: float | None = None,
                 refresh_distance: float = 0.25, background_refresh: bool = False, blas: bool | None = None,
                 threads: int | None = None):
        self._config = config or ArrayConfig()
        check_config(rom, self._config)
        self.rom = rom
        #: Number of units.
        self.n_units = self._config.n_units
        self.fe = fe or ArrayTwin(self._config, settings)
        model = self.model = self.fe.model
        if rom.basis.shape[0] != model.disc.n_dofs:
            raise RomMismatchError(f"ROM basis has {rom.basis.shape[0]} dofs, the mesh {model.disc.n_dofs}")
        env = rom.envelope
        self.modes = env.modes
        self._driven = env.driven
        self._nd = nd = self._driven.size
        self._slot = np.full(self.n_units, -1)  # each driven unit's place among the displacement inputs
        self._slot[self._driven] = np.arange(nd)
        self._biased_of: dict[tuple, np.ndarray | None] = {self.modes: self._driven[:0]}
        self._nc = 1 + nd + rom.n_modes
        self._vectors = np.ascontiguousarray(np.hstack([rom.lift, rom.basis]))
        full = np.hstack([rom.reference[:, None], self._vectors])
        self._fmap = point_maps(model.disc, rom.point_element, rom.point_index, full).astype(MAP_DTYPE)
        self._wmap = point_maps(model.disc, rom.point_element, rom.point_index, rom.enrichment).astype(MAP_DTYPE)
        self._xi = np.ascontiguousarray(rom.point_weight)
        self._unit = np.ascontiguousarray(model.mesh.element_unit[rom.point_element])
        self._held = np.ascontiguousarray(held_elements(model, self.modes)[rom.point_element])
        self._centre = full[3 * model.mesh.centre_nodes + 2]  # (n_units, nc): centre z of [1, d, q]
        cfg = self._config
        self._cap_factor = cfg.permittivity / cfg.thickness**2
        self._maxwell_factor = 0.5 * cfg.permittivity / cfg.thickness**2
        self._output_scale = np.concatenate([rom.force_reference[self._driven], model.flat_capacitance])
        self._lo = np.where(np.isnan(env.displacement_min), -np.inf, env.displacement_min)
        self._hi = np.where(np.isnan(env.displacement_max), np.inf, env.displacement_max)
        self._range = np.concatenate([(env.displacement_max - env.displacement_min)[self._driven],
                                      self._maxwell_factor * (env.voltage_max**2 - env.voltage_min**2)])
        self._range[self._range <= 0] = np.inf
        self._train = rom.train_parameters.copy()
        self._train[:, nd:] = self._maxwell_factor * self._train[:, nd:] ** 2  # voltages as Maxwell coefficients
        self._buffers = tuple(np.empty(k) for k in (self._nc, self.n_units, rom.enrichment.shape[1], self.n_units))
        self._points = (self._fmap, self._wmap, self._xi, self._unit, self._held, model.yeoh.c10, model.yeoh.c20,
                        model.yeoh.c30)
        if threads is None:
            big = self._fmap.nbytes + self._wmap.nbytes >= TEAM_BYTES
            cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
            threads = 2 if big and cpus >= 2 else 1
        self.team = PointTeam(self._points, threads, self.n_units)
        self._layout = (self._driven, np.ascontiguousarray(self._centre), self._maxwell_factor, cfg.thickness,
                        self._output_scale, self._range, SECANT_STEP if not background_refresh else np.inf)
        self._bounds = (self._lo, self._hi, env.voltage_min, env.voltage_max, self._driven, self._maxwell_factor)
        self._take(cfg)
        self._flat_capacitance = model.flat_capacitance
        self._reference = rom.reference
        self._zeros = np.zeros(self.n_units)  # velocity, bias and external force without biased units
        self._zeros.flags.writeable = False
        self._none = np.zeros(self.n_units, dtype=bool)  # lifted_off: the reduced model answers units in contact
        self._none.flags.writeable = False
        self.tolerance = float(tolerance if tolerance is not None else rom.tolerance)
        self.second_step = float(second_step if second_step is not None else min(1e-3, self.tolerance))
        self.refresh_distance = refresh_distance
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="rom-tangent") if background_refresh else None
        blas = not background_refresh if blas is None else blas
        self._blas = blas and self._nc + rom.enrichment.shape[1] >= BLAS_COLUMNS
        self._refresh_step = refresh_distance * self._range
        self.fallbacks: Counter = Counter()
        self.updates = self.evaluations = self.refreshes = self.resyncs = 0
        self._seconds = 0.0  # share of the recent updates that evaluated twice (_count_seconds)
        self._resync: TwinResult | None = None
        self.reset()

    @property
    def blas_products(self) -> bool:
        """Whether this twin's Hessian refreshes are BLAS products (else summed point by point)."""
        return self._blas

    @property
    def config(self) -> ArrayConfig:
        """The array; may be replaced by one that differs only in :data:`~.reduced.UNCHECKED_FIELDS`
        (the command limits a node changes at run time), else :class:`RomMismatchError`."""
        return self._config

    @config.setter
    def config(self, cfg: ArrayConfig) -> None:
        if cfg is self._config:  # the node sets it before every update: no hash for the same object
            return
        check_config(self.rom, cfg)
        self._config = self.fe.config = cfg
        self._take(cfg)

    def _take(self, cfg: ArrayConfig) -> None:
        """Read what an update uses of the config: command limits and the units' bias, mass, damping, contact."""
        self._limit = cfg.scaled("max_displacement")
        self._breakdown = cfg.breakdown_field
        self._laws, self._mass, self._damping = cfg.per_unit("bias"), cfg.per_unit("mass"), cfg.per_unit("damping")
        self._contact = [k for k, on in enumerate(cfg.per_unit("contact")) if on]

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the reduced and the FE kernels now, not in the first update.

        The FE twin's :meth:`~.ArrayTwin.warm_up`, then one checked reduced solve at the
        envelope's centre and :meth:`reset`; the counters are zeroed: the twin is left
        as a new one.
        """
        self.fe.warm_up()
        env = self.rom.envelope
        centre = np.where(np.isnan(env.displacement_min), 0.0, 0.5 * (env.displacement_min + env.displacement_max))
        self.solve(centre, 0.5 * (env.voltage_min + env.voltage_max), check_stability=True)
        if self._nd:  # the biased heights' kernel: one height update on copies of the state, thrown away
            n, t, units = self.n_units, self._tangent, self._driven[:1]
            with self.team as team:
                heights(self._points, self._z.copy(), self._maxwell, self._displacement.copy(), self._voltage,
                        self._layout, t.arrays, (t.outputs, t.centre), self._cap_factor, self.second_step,
                        self._buffers, np.empty(n), np.empty((5, n)), np.empty(7),
                        (self._forces, units, self._slot[units], self._forces[units].copy(), np.zeros(1)), True,
                        True, 1, np.empty(4), team.arrays)
        self.reset()
        self.fallbacks.clear()
        self.updates = self.evaluations = self.refreshes = self.resyncs = 0

    def reset(self) -> None:
        """Flat pre-stretched state at 0 V in the trained modes; the next solve starts cold."""
        self.fe.reset()
        n = self.n_units
        self._modes = self.modes
        self._displacement = np.zeros(n)  # driven: command, biased: height w, free: centre deflection [m]
        self._voltage = np.zeros(n)
        self._force = np.zeros(n)  # commanded external force on biased indenters [N]
        self._forces = np.zeros(n)  # indenter forces of the last reduced result [N] (the heights' predictor)
        self._lifted = np.zeros(n, dtype=bool)  # indenters an FE answer found lifted off
        self._velocity = self._acceleration = self._zeros  # dw/dt [m/s], d2w/dt2 [m/s^2] (Newmark state)
        self._z = np.zeros(self._nc)
        self._z[0] = 1.0
        self._maxwell = np.zeros(n)
        self._tangent: _Tangent | None = None
        self._tangent_at = np.zeros(self._range.size)
        self._cold = True
        self._projected = False  # whether ``_z`` holds a state to start a cold solve from
        self._refresh_next = False
        self._pending: Future | None = None  # a background refresh from before is dropped
        self.last: TwinResult | None = None
        self._fe_answer: TwinResult | None = None  # the last result the FE gave (its state is the twin's)

    # ------------------------------------------------------------------ pieces
    def _command(self, name: str, values, default: np.ndarray) -> np.ndarray:
        """A per-unit command as a new float array (one value for every unit is broadcast)."""
        if values is None:
            return default.copy()
        arr = np.array(values, dtype=float)
        if arr.shape != (self.n_units,):
            if arr.ndim != 0:
                raise ValueError(f"{name} must have one value per unit ({self.n_units}), got shape {arr.shape}")
            arr = np.full(self.n_units, float(arr))
        return arr

    def _evaluate(self, z: np.ndarray, maxwell: np.ndarray, out: tuple) -> tuple[float, float]:
        self.evaluations += 1
        return evaluate(self._fmap, self._wmap, self._xi, self._unit, self._held, z, maxwell, self.model.yeoh, out)

    def _tangent_of(self, z: np.ndarray, maxwell: np.ndarray) -> tuple[_Tangent, np.ndarray]:
        """The tangent at ``(z, maxwell)`` and where it was taken (reads no mutable state: thread-safe)."""
        hz, hm = hessian(self._fmap, self._wmap, self._xi, self._unit, z, maxwell, self.model.yeoh, self.n_units,
                         blas=self._blas)
        return _Tangent(self, hz, hm), np.concatenate([z[1:1 + self._nd], maxwell])

    def _refresh(self, z: np.ndarray, maxwell: np.ndarray) -> _Tangent:
        """Refresh the tangent now, at ``(z, maxwell)``."""
        self._install(*self._tangent_of(z, maxwell))
        return self._tangent

    def _install(self, tangent: _Tangent, at: np.ndarray) -> None:
        self.refreshes += 1
        self._tangent, self._tangent_at = tangent, at
        self._refresh_next = False

    def _request_refresh(self, z: np.ndarray, maxwell: np.ndarray) -> int:
        """Refresh now (returns 1), or with ``background_refresh`` start one in the worker thread (returns 0)."""
        if self._pool is None:
            self._refresh(z, maxwell)
            return 1
        if self._pending is None:
            self._pending = self._pool.submit(self._tangent_of, z.copy(), maxwell.copy())
        self._refresh_next = False
        return 0

    def check_in_background(self) -> Future | None:
        """Judge whether the current reduced state is a stable minimum in the worker thread (``background_refresh``).

        The Hessian at the state is computed there, where ``check_stability`` computes it in the
        calling thread (57 ms on the 200-mode 4-by-4, a real-time twin's Hessian being summed
        without BLAS); if no refresh is under way it is also the next one.  The returned future's
        result is the verdict of ``TwinResult.stable`` (``H_qq`` positive definite).

        Returns None without a worker thread, before a reduced state (a reset, a cold start to
        come), when the FE answered the last update, or with biased units (their verdict needs
        their bias laws' slopes: a checked :meth:`solve`).
        """
        biased = self._biased_units(self._modes)
        if (self._pool is None or self.last is None or self._cold or self.last is self._fe_answer
                or biased is None or biased.size):
            return None
        job = self._pool.submit(self._tangent_of, self._z.copy(), self._maxwell.copy())
        if self._pending is None:
            self._pending = job
        return verdict_of(job, lambda done: bool(done[0].stable))

    def _collect_refresh(self) -> int:
        """Install a background refresh that has finished (returns 1 if one was)."""
        if self._pending is None or not self._pending.done():
            return 0
        pending, self._pending = self._pending, None
        self._install(*pending.result())
        return 1

    @property
    def threads(self) -> int:
        """Threads sharing an update's evaluations, the caller included (:class:`.point_team.PointTeam`)."""
        return self.team.n_threads

    def close(self) -> None:
        """Stop the background refresh thread and the helper threads (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        self.team.close()

    def _settle(self, z: np.ndarray, maxwell: np.ndarray, from_state: bool,
                cancel: Callable[[], bool] | None = None) -> tuple[int, int]:
        """Newton on ``q`` to convergence at fixed ``(d, m)`` (in place); returns (evaluations, refreshes).

        Starts from ``z``'s coordinates if ``from_state`` (a projected FE state, or the
        state a large jump left), else from the training snapshot nearest to ``(d, m)``
        (distances scaled by the envelope).
        """
        nd = self._nd
        q = slice(1 + nd, self._nc)
        if not from_state:
            p = np.concatenate([z[1:1 + nd], maxwell])
            i = int(np.argmin(np.sum(((self._train - p) / self._range) ** 2, axis=1)))
            z[q] = self.rom.train_coordinates[i]
        tol = 1e-9 * self.model.length_scale
        out = self._buffers
        tangent, refreshes, last = None, 0, 0.0  # (the first step: no contraction measured yet)
        for iteration in range(1, 31):
            if cancel is not None and cancel():
                raise SolveCancelled("reduced solve cancelled")
            if tangent is None:
                tangent = self._refresh(z, maxwell)
                refreshes += 1
            self._evaluate(z, maxwell, out)
            dq = -tangent.hqq_inv @ out[0][q]
            if not np.isfinite(dq).all():
                break
            z[q] += dq
            size = np.abs(dq).max()
            if size <= tol:
                return iteration, refreshes
            if size > SETTLE_CONTRACTION * last:  # converging slowly: a new Hessian for the next step
                tangent = None
            last = size
        raise ConvergenceError("reduced Newton did not converge")

    def _project(self, x: np.ndarray, d: np.ndarray, v: np.ndarray) -> None:
        """Make positions ``x`` [m] at command ``(d, v)`` the start of the next (cold) reduced solve."""
        z = self._z.copy()
        driven = d[self._driven]
        z[1:1 + self._nd] = driven
        z[1 + self._nd:] = project(self.rom.basis, x - combine(self.rom.reference, self.rom.lift, driven))
        self._z, self._maxwell = z, self._maxwell_factor * v * v
        self._projected = self._cold = True

    def request_resync(self, result: TwinResult) -> None:
        """Restart the reduced state from an FE result at the next :meth:`solve` (callable from another thread).

        The FE check of a node calls this when the reduced model has drifted from the FE:
        the next solve runs Newton from ``result``'s state projected on the basis.  A
        result in other unit modes or outside the envelope is ignored.
        """
        self._resync = result

    def _apply_resync(self) -> None:
        result, self._resync = self._resync, None
        d, v = np.asarray(result.displacement, float), np.asarray(result.voltage, float)
        biased = self._biased_units(tuple(result.modes))
        if biased is not None and self.rom.envelope.violation(d, v, self.modes) is None:
            self._project(np.asarray(result.positions).ravel(), d, v)
            self._displacement = self._displacement.copy()
            self._displacement[biased] = d[biased]  # a biased unit's height is state: the FE's
            self.resyncs += 1

    # ------------------------------------------------------------------ solve
    def solve(self, displacement: Sequence[float] | float | None = None,
              voltage: Sequence[float] | float | None = None,
              modes: Sequence[str] | None = None, check_stability: bool | None = None,
              cancel: Callable[[], bool] | None = None, force: Sequence[float] | float | None = None) -> TwinResult:
        """Move to a new command and return the state there (see :meth:`.ArrayTwin.solve`).

        Answered by the reduced model inside the envelope, by the FE otherwise
        (``result.fallback`` says why).  ``modes`` defaults to the previous ones (the
        trained modes after :meth:`reset`); a unit trained as driven may be ``"biased"``
        (its height solved for, :meth:`_balance`), with its bias law, ``contact`` from the
        config and ``force`` the external force on its indenter [N] (default: the previous
        one).  ``check_stability`` (default False) refreshes the reduced Hessian at the new
        state and reports whether it is positive definite (with biased units: and the
        condensed ``K - dB/dw``).  ``cancel`` is asked between reduced Newton iterations (a
        jump or a cold start) and by an FE fallback; when it returns True the solve
        raises :class:`SolveCancelled` and the twin keeps its previous state.

        Raises
        ------
        ValueError
            For a command of the wrong length, with NaN/inf, beyond ``max_displacement``,
            or with invalid modes.
        ConvergenceError
            When the FE fallback finds no equilibrium.
        SolveCancelled
            When ``cancel`` asked for it.
        """
        return self._advance(displacement, voltage, force, modes, check_stability, cancel, None)

    def step(self, dt: float, displacement: Sequence[float] | float | None = None,
             voltage: Sequence[float] | float | None = None, force: Sequence[float] | float | None = None,
             modes: Sequence[str] | None = None, check_stability: bool | None = None,
             cancel: Callable[[], bool] | None = None) -> TwinResult:
        """Advance the dynamics by ``dt`` [s] with the commands held at their new values (see :meth:`.ArrayTwin.step`).

        Biased units with ``mass > 0`` move by ``m w'' + c w' = B(w) + f - F(w, V)``
        (Newmark average acceleration, :mod:`.dynamics`): their generalised force in
        :meth:`_balance` is ``G = B + f - m a(w) - c v(w)``, so ``K - dG/dw`` gains the
        inertial stiffness ``m / (beta dt^2)``; the membrane and massless units are
        quasi-static.  An update the reduced model cannot answer is a step of the FE twin
        from the reduced state (:meth:`.ArrayTwin.adopt`).
        """
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite time step > 0 s, got {dt}")
        return self._advance(displacement, voltage, force, modes, check_stability, cancel, float(dt))

    def _advance(self, displacement, voltage, force, modes, check_stability: bool | None,
                 cancel: Callable[[], bool] | None, dt: float | None) -> TwinResult:
        """A solve (``dt`` None) or a time step to the commands, by the reduced model or the FE."""
        tic = time.perf_counter()
        if self._resync is not None:
            self._apply_resync()
        d1 = self._command("displacement", displacement, self._displacement)
        v1 = self._command("voltage", voltage, self._voltage)
        f1 = self._command("force", force, self._force)
        modes = self._modes if modes is None else tuple(modes)
        biased = self._biased_units(modes)
        outside = infinite = False
        if biased is not None:  # the heights start where they are (a guess: kept in the envelope)
            for k in biased.tolist():
                w = self._displacement[k]
                d1[k] = min(max(w, self._lo[k]), self._hi[k])
                outside = outside or d1[k] != w
                infinite = infinite or not math.isfinite(f1[k])
        code, moved = classify(d1, v1, self._limit, self._bounds, self._tangent_at, self._refresh_step)
        if code == 1 or infinite:
            raise ValueError(f"displacement, voltage and force must be finite, got {d1.tolist()} m, "
                             f"{v1.tolist()} V, {f1.tolist()} N")
        if code == 2:
            raise ValueError(f"displacement {d1.tolist()} m exceeds max_displacement ({self._limit} m)")
        if code == 3 or biased is None:
            modes = self.model.check_modes(modes)
            reason = self.rom.envelope.violation(d1, v1, modes if biased is None else self.modes)
            reason = reason or "outside the envelope"
            return self._fallback("envelope", reason, d1, v1, modes, check_stability, cancel, tic, f1, dt)
        try:
            result = self._reduced(d1, v1, moved, bool(check_stability), cancel, tic, modes, biased, f1, dt)
        except SolveCancelled:
            raise
        except ConvergenceError as exc:
            return self._fallback("newton", str(exc), d1, v1, modes, check_stability, cancel, tic, f1, dt)
        except _Refused as exc:  # from heights outside the envelope a refusal is the envelope's, whatever it says
            kind, reason = ("envelope", f"biased heights start outside the envelope ({exc})") if outside else (
                exc.kind, str(exc))
            return self._fallback(kind, reason, d1, v1, modes, check_stability, cancel, tic, f1, dt)
        if result.error_indicator > self.tolerance:
            return self._fallback("indicator", f"error indicator {result.error_indicator:.3g} above tolerance "
                                  f"{self.tolerance:.3g}", d1, v1, modes, check_stability, cancel, tic, f1, dt,
                                  indicator=result.error_indicator)
        self.updates += 1
        self.last = result
        return result

    def answers(self, modes: Sequence[str]) -> bool:
        """Whether the reduced model can answer unit ``modes``: its trained modes, with any unit trained as
        driven made biased (other modes go to the FE)."""
        return self._biased_units(tuple(modes)) is not None

    def _biased_units(self, modes: tuple) -> np.ndarray | None:
        """The biased units of ``modes`` (empty for the trained modes), or None if the ROM cannot answer them:
        it answers its trained modes with any unit trained as driven made biased."""
        units = self._biased_of.get(modes)
        if units is None and modes not in self._biased_of:
            fits = len(modes) == self.n_units and all(
                m == e or (m == BIASED and e == DRIVEN) for m, e in zip(modes, self.modes))
            units = np.array([k for k, m in enumerate(modes) if m == BIASED], dtype=np.int64) if fits else None
            self._biased_of[modes] = units
        return units

    def _loads(self, units: np.ndarray, f1: np.ndarray, dt: float | None) -> list[UnitLoad]:
        """What pushes each biased indenter of ``units`` (:class:`.UnitLoad`): its bias law and external force,
        and in a time step of ``dt`` [s] the inertia and damping of a unit with mass (:class:`.NewmarkStep`)."""
        laws, mass, damping = self._laws, self._mass, self._damping
        return [UnitLoad(laws[k], f1[k], f1[k], newmark=None if dt is None or mass[k] <= 0 else NewmarkStep(
            mass[k], damping[k], dt, self._displacement[k], self._velocity[k], self._acceleration[k]))
            for k in units]

    @staticmethod
    def _push(loads: list[UnitLoad], w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``G_k(w_k)`` [N] and ``dG_k/dw_k`` [N/m] of each load at the heights ``w`` [m]."""
        g, dg = np.empty(len(loads)), np.empty(len(loads))
        try:
            for i, load in enumerate(loads):
                g[i], dg[i] = load(w[i], 1.0)
        except BiasRangeError as exc:
            raise _Refused("envelope", f"bias table: {exc}") from None
        return g, dg

    def _count_seconds(self, updates: int, evaluations: int) -> None:
        """Follow the share of updates that evaluate twice (an average over about the last 1 /
        :data:`SECONDS_WEIGHT` updates)."""
        if updates > 0:
            share = min(1.0, (evaluations - updates) / updates)
            self._seconds += SECONDS_WEIGHT * (share - self._seconds)

    def _update(self, z: np.ndarray, m0: np.ndarray, d1: np.ndarray, v1: np.ndarray, m1: np.ndarray,
                result: np.ndarray, info: np.ndarray, cancel: Callable[[], bool] | None) -> tuple[int, int]:
        """One reduced update of ``z`` to ``(d1, v1)`` (:func:`.rom_kernels.update`), converged with refreshed
        Hessians when it is a jump; returns (evaluations, refreshes)."""
        defer = self._seconds > DEFER_SHARE
        with self.team as team:
            update(self._points, z, m0, d1, v1, self._layout, self._tangent.arrays, self._cap_factor,
                   self.second_step, self._buffers, m1, result, info, team.arrays, defer)
        self.evaluations += int(info[4])
        evals, refreshes = int(info[4]), 0
        self._count_seconds(1, evals)
        self._refresh_next = info[5] > 0.0
        if info[6] > self.second_step:  # a jump: the last correction still moved an output, so converge
            more, refreshes = self._settle(z, m1, True, cancel)  # (counts its own evaluations)
            with self.team as team:
                update(self._points, z, m1, d1, v1, self._layout, self._tangent.arrays, self._cap_factor,
                       self.second_step, self._buffers, m1, result, info, team.arrays, defer)
            self.evaluations += int(info[4])
            evals += more + int(info[4])
        return evals, refreshes

    def _balance(self, z: np.ndarray, m0: np.ndarray, d1: np.ndarray, v1: np.ndarray, m1: np.ndarray,
                 result: np.ndarray, info: np.ndarray, units: np.ndarray, loads: list[UnitLoad], predict: bool,
                 cancel: Callable[[], bool] | None) -> tuple[int, int, np.ndarray | None]:
        """Update to ``(d1, v1)`` with the heights ``w = d1[units]`` of the biased units solved for,
        ``F_k(q(d), d) = G_k(w_k)``; returns (evaluations, refreshes, the heights' linear prediction or None).

        Newton on the heights in one compiled call (:func:`.rom_kernels.heights`: the
        condensed stiffness ``K = H_dd - H_dq H_qq^-1 H_qd`` of the refreshed Hessian,
        ``dw = (K - dG/dw)^-1 (G - F)``, each iterate one reduced update, the last step
        applied to first order) with ``G`` linearised at the start heights; the bias
        laws are then evaluated at the result, and a law that is not affine there (a
        table) is linearised again.  A jump in ``q`` converges with refreshed Hessians
        between calls.  ``K - dG/dw`` not positive definite at an iterate (a limit point:
        snap-through or instability) is :class:`_Refused`; no convergence within
        :data:`MAX_HEIGHT_ITERATIONS` updates a :class:`ConvergenceError`.
        """
        slots = self._slot[units]
        w = d1[units]
        g, dg = self._push(loads, w)
        status = np.empty(3 + units.size)
        biased = (self._forces, units, slots, g - dg * w, dg)
        evals = refreshes = 0
        budget, first, predicted = MAX_HEIGHT_ITERATIONS, True, None
        per_call = budget if all(load.law.affine for load in loads) else 1  # else G linearised at every iterate
        while True:
            tangent = self._tangent
            with self.team as team:
                heights(self._points, z, m0, d1, v1, self._layout, tangent.arrays, (tangent.outputs, tangent.centre),
                        self._cap_factor, self.second_step, self._buffers, m1, result, info, biased, predict, first,
                        min(per_call, budget), status, team.arrays, self._seconds > DEFER_SHARE)
            done = int(status[0])
            self._count_seconds(int(status[1]), done)
            self.evaluations += done
            evals, budget, code = evals + done, budget - int(status[1]), status[2]
            self._refresh_next = self._refresh_next or info[5] > 0.0
            if predict:
                predicted, predict = status[3:].copy(), False
            if code == 0.0 and per_call > 1:  # affine laws: G was exact
                return evals, refreshes, predicted
            if code == 1.0:
                raise _Refused("snap", f"units {(units + 1).tolist()} at heights {d1[units].tolist()} m: K - dG/dw "
                                       "is not positive definite (a limit point: snap-through or instability)")
            if budget <= 0 and code != 0.0:
                raise ConvergenceError(f"the heights of biased units {(units + 1).tolist()} did not converge in "
                                       f"{MAX_HEIGHT_ITERATIONS} reduced updates")
            first, m0 = code == 3.0, m1.copy()  # first: moved by a step not yet evaluated
            if code == 2.0:  # a jump in q: converge it, then update again there
                more, refreshed = self._settle(z, m1, True, cancel)
                more_too, refreshed_too = self._update(z, m0, d1, v1, m1, result, info, cancel)
                evals, refreshes, budget = evals + more + more_too, refreshes + refreshed + refreshed_too, budget - 1
                continue
            w = d1[units]
            g, dg = self._push(loads, w)
            if code == 0.0 and np.all(np.abs(g - biased[3] - biased[4] * w) <= self.second_step *
                                      self._output_scale[slots]):
                return evals, refreshes, predicted
            biased = (self._forces, units, slots, g - dg * w, dg)  # G linearised at the new heights

    def _reduced(self, d1: np.ndarray, v1: np.ndarray, moved: float, check: bool, cancel: Callable[[], bool] | None,
                 tic: float, modes: tuple, units: np.ndarray, f1: np.ndarray, dt: float | None) -> ReducedResult:
        if self._lifted.any():
            raise _Refused("contact", f"the indenters of units {(np.flatnonzero(self._lifted) + 1).tolist()} are "
                                      "lifted off: the FE answers until they touch down")
        loads = self._loads(units, f1, dt) if units.size else []
        z = self._z.copy()
        m0 = self._maxwell
        evals = refreshes = 0
        cold = self._cold
        if cold:
            m0 = self._maxwell_factor * v1 * v1
            z[1:1 + self._nd] = d1[self._driven]
            evals, refreshes = self._settle(z, m0, self._projected, cancel)
            self._cold = self._projected = False
        else:
            refreshes = self._collect_refresh()
            if moved > STALE_LIMIT and self._pool is not None and not refreshes:  # the worker lags too far
                self._pending = None  # (older than the tangent taken here: dropped when it ends)
                self._refresh(z, m0)
                refreshes += 1
            elif moved > 1.0 or self._refresh_next:
                refreshes += self._request_refresh(z, m0)
        m1, result, info = np.empty(self.n_units), np.empty((5, self.n_units)), np.empty(7)
        bias_force = external = self._zeros
        if units.size:
            more, refreshed, predicted = self._balance(z, m0, d1, v1, m1, result, info, units, loads, not cold, cancel)
            evals, refreshes = evals + more, refreshes + refreshed
            self._check_heights(d1, units, predicted)
            bias_force, external = np.zeros(self.n_units), np.zeros(self.n_units)
            for k, load in zip(units.tolist(), loads):  # scalars: a few units, cheaper than numpy's fancy indexing
                bias_force[k], external[k] = load.law.force(float(d1[k])), f1[k]
        else:
            more, refreshed = self._update(z, m0, d1, v1, m1, result, info, cancel)
            evals, refreshes = evals + more, refreshes + refreshed
        self._check_contact(result[0])
        stable = None
        if check:
            tangent = self._refresh(z, m1)
            refreshes += 1
            slots = self._slot[units]
            dg = [load.law.slope(w) for load, w in zip(loads, d1[units])]
            stable = tangent.stable and _positive_definite(tangent.outputs[np.ix_(slots, slots)] - np.diag(dg))
        velocity, acceleration = self._zeros, self._zeros
        if dt is not None:
            velocity, acceleration = (result[3] - self._displacement) / dt, np.zeros(self.n_units)
            for k, load in zip(units, loads):
                if load.newmark is not None:
                    velocity[k], acceleration[k] = load.newmark.velocity(d1[k]), load.newmark.acceleration(d1[k])
        self._velocity, self._acceleration = velocity, acceleration
        self._z, self._maxwell, self._voltage, self._displacement = z, m1, v1, result[3]
        self._modes, self._force, self._forces = modes, f1, result[0]
        peak, sigma_min = result[4], float(info[1])
        return ReducedResult(
            displacement=result[3].copy(), voltage=v1, modes=modes, force=result[0], capacitance=result[1],
            delta_capacitance=result[1] - self._flat_capacitance, centre_deflection=result[2], peak_field=peak,
            energy=float(info[0]), min_principal_stress=sigma_min, wrinkled=sigma_min < 0,
            field_exceeded=bool(peak.max() > self._breakdown), stable=stable, iterations=evals,
            factorisations=refreshes, step_cuts=0, residual=float(info[3]), solve_time=time.perf_counter() - tic,
            velocity=velocity, bias_force=bias_force, external_force=external, lifted_off=self._none, snaps=(),
            error_indicator=float(info[2]) * self.rom.indicator_scale,
            recover=functools.partial(_recover, self._reference, self._vectors, z[1:]))

    def _check_heights(self, d1: np.ndarray, units: np.ndarray, predicted: np.ndarray | None) -> None:
        """Refuse biased heights outside the trained range, or converged more than the FE's ``jump_tol`` (a
        fraction of D) from their linear prediction (a jump to another branch, as :mod:`.snap` takes it)."""
        jump = self.fe.solver.settings.jump_tol * self.model.length_scale
        for i, k in enumerate(units.tolist()):  # a few units: plain Python is faster than numpy here
            w, lo, hi = float(d1[k]), float(self._lo[k]), float(self._hi[k])
            if not lo - 1e-9 * (hi - lo) <= w <= hi + 1e-9 * (hi - lo):
                raise _Refused("envelope", f"height {w:.6g} m of biased unit {k + 1} outside the trained "
                                           f"[{lo:.6g}, {hi:.6g}] m")
            if predicted is not None and abs(w - predicted[i]) > jump:
                raise _Refused("snap", f"biased heights {d1[units].tolist()} m of units {(units + 1).tolist()} "
                                       f"converged more than {jump:.3g} m from their linear prediction "
                                       f"{predicted.tolist()} m (a jump: a limit point crossed?)")

    def _check_contact(self, force: np.ndarray) -> None:
        """Refuse a state where an indenter with unilateral ``contact`` would pull the membrane: it lifts off
        (:class:`.ArrayTwin` releases it; the reduced model has its disk held)."""
        if not self._contact:
            return
        tolerance = self.fe.solver.settings.residual_tol * self.model.force_scale
        pulling = [k for k in self._contact if force[k] < -tolerance]
        if pulling:
            raise _Refused("contact", f"the indenters of units {[k + 1 for k in pulling]} would pull the "
                                      f"membrane ({force[pulling].tolist()} N): lift-off")

    def _fallback(self, kind: str, reason: str, d1: np.ndarray, v1: np.ndarray, modes: tuple,
                  check_stability: bool | None, cancel: Callable[[], bool] | None, tic: float,
                  f1: np.ndarray, dt: float | None, indicator: float = math.nan) -> ReducedResult:
        """Answer with the FE, from the reduced state if the reduced model answered last (the FE's path, its
        snap detection and a time step start where the twin is); resynchronise the reduced state from it
        when the command is in the envelope."""
        if self.last is not None and self.last is not self._fe_answer:  # the reduced model answered last
            self.fe.adopt(self.last, self._acceleration)
        if dt is None:
            res = self.fe.solve(d1, v1, modes, check_stability, cancel=cancel, force=f1)
        else:
            res = self.fe.step(dt, d1, v1, f1, modes, check_stability, cancel=cancel)
        self._velocity, self._acceleration = np.array(res.velocity), self.fe.acceleration
        self.fallbacks[kind] += 1
        self._modes, self._displacement, self._voltage, self._force = res.modes, res.displacement.copy(), v1, f1
        self._lifted = np.asarray(res.lifted_off, dtype=bool).copy()
        if kind not in ("envelope", "contact"):
            self._project(res.positions.ravel(), res.displacement, v1)
        else:
            self._projected = False
        self._cold = True
        values = {f.name: getattr(res, f.name) for f in fields(TwinResult)}
        values["solve_time"] = time.perf_counter() - tic
        self.last = self._fe_answer = ReducedResult(error_indicator=indicator, fallback=f"{kind}: {reason}",
                                                    **values)
        return self.last
