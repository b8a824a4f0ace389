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
   from the FE state projected on the basis.

**Error indicator**: the residual along the enrichment vectors ``W`` (next POD modes and
the linear responses to each input that the basis was not built from),
``g_w = dE/dw``, is the part of the equilibrium the basis cannot represent.  Solving the
enriched linear problem with ``H`` gives the change of the outputs had ``W`` been in the
basis,

    delta_o = (H_oq H_qq^-1 H_qw - H_ow) S^-1 g_w,     S = H_ww - H_wq H_qq^-1 H_qw,

and the indicator is the largest ``|delta F_k| / F_ref_k`` or ``|delta C_u| / C_u``.

**Fallback**: a command outside the trained envelope (or with other unit modes), an
indicator above ``tolerance``, or a reduced Newton that fails is answered by the FE twin
(``result.fallback`` says why; :attr:`ReducedTwin.fallbacks` counts them), and the
reduced state is resynchronised from the FE state.
"""

from __future__ import annotations

import functools
import math
import time
from collections import Counter
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, fields
from typing import Callable, Sequence

import numpy as np

from .config import ArrayConfig
from .reduced import ReducedModel, RomMismatchError, check_config
from .rom_build import held_elements
from .rom_kernels import classify, evaluate, hessian, point_maps, reduced_tangent, update
from .solver import ConvergenceError, NewtonSettings, SolveCancelled
from .twin import ArrayTwin, TwinResult


def _recover(reference: np.ndarray, vectors: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Full positions (n_nodes, 3) [m] of reduced coefficients ``z`` over ``[lift, basis]``."""
    return (reference + vectors @ z).reshape(-1, 3)


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
    """The reduced Hessian at one state and what an update derives from it (:func:`.rom_kernels.reduced_tangent`)."""

    def __init__(self, twin: "ReducedTwin", hz: np.ndarray, hm: np.ndarray):
        self.stable, self.arrays = reduced_tangent(hz, hm, twin._nd, twin.rom.n_modes, twin._cap_factor,
                                                   twin._output_scale)
        self.hqq_inv = self.arrays[1]


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

    Attributes
    ----------
    fallbacks : Counter
        Updates the FE answered, by reason: ``"envelope"``, ``"indicator"``, ``"newton"``.
    updates, evaluations, refreshes, resyncs : int
        Reduced updates answered, gradient evaluations, Hessian refreshes and restarts
        from an FE state (:meth:`request_resync`) so far.
    """

    def __init__(self, config: ArrayConfig | None, rom: ReducedModel, settings: NewtonSettings | None = None,
                 tolerance: float | None = None, fe: ArrayTwin | None = None, second_step: float | None = None,
                 refresh_distance: float = 0.25, background_refresh: bool = False):
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
        self._nc = 1 + nd + rom.n_modes
        self._vectors = np.ascontiguousarray(np.hstack([rom.lift, rom.basis]))
        full = np.hstack([rom.reference[:, None], self._vectors])
        self._fmap = point_maps(model.disc, rom.point_element, rom.point_index, full)
        self._wmap = point_maps(model.disc, rom.point_element, rom.point_index, rom.enrichment)
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
        self._layout = (self._driven, np.ascontiguousarray(self._centre), self._maxwell_factor, cfg.thickness,
                        self._output_scale)
        self._bounds = (self._lo, self._hi, env.voltage_min, env.voltage_max, self._driven, self._maxwell_factor)
        self._limit = cfg.scaled("max_displacement")
        self._breakdown = cfg.breakdown_field
        self._flat_capacitance = model.flat_capacitance
        self._reference = rom.reference
        self._zeros = np.zeros(self.n_units)  # velocity, bias and external force: no biased units, quasi-static
        self._zeros.flags.writeable = False
        self._none = np.zeros(self.n_units, dtype=bool)  # lifted_off: no contact without biased units
        self._none.flags.writeable = False
        self.tolerance = float(tolerance if tolerance is not None else rom.tolerance)
        self.second_step = float(second_step if second_step is not None else min(1e-3, self.tolerance))
        self.refresh_distance = refresh_distance
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="rom-tangent") if background_refresh else None
        self._refresh_step = refresh_distance * self._range
        self.fallbacks: Counter = Counter()
        self.updates = self.evaluations = self.refreshes = self.resyncs = 0
        self._resync: TwinResult | None = None
        self.reset()


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
        self._limit = cfg.scaled("max_displacement")
        self._breakdown = cfg.breakdown_field

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
        self.reset()
        self.fallbacks.clear()
        self.updates = self.evaluations = self.refreshes = self.resyncs = 0

    def reset(self) -> None:
        """Flat pre-stretched state at 0 V in the trained modes; the next solve starts cold."""
        self.fe.reset()
        n = self.n_units
        self._modes = self.modes
        self._displacement = np.zeros(n)
        self._voltage = np.zeros(n)
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
        hz, hm = hessian(self._fmap, self._wmap, self._xi, self._unit, z, maxwell, self.model.yeoh, self.n_units)
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

    def _collect_refresh(self) -> int:
        """Install a background refresh that has finished (returns 1 if one was)."""
        if self._pending is None or not self._pending.done():
            return 0
        pending, self._pending = self._pending, None
        self._install(*pending.result())
        return 1

    def close(self) -> None:
        """Stop the background refresh thread (if any)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)

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
        for iteration in range(1, 31):
            if cancel is not None and cancel():
                raise SolveCancelled("reduced solve cancelled")
            tangent = self._refresh(z, maxwell)
            self._evaluate(z, maxwell, out)
            dq = -tangent.hqq_inv @ out[0][q]
            if not np.isfinite(dq).all():
                break
            z[q] += dq
            if np.abs(dq).max() <= tol:
                return iteration, iteration
        raise ConvergenceError("reduced Newton did not converge")

    def _project(self, x: np.ndarray, d: np.ndarray, v: np.ndarray) -> None:
        """Make positions ``x`` [m] at command ``(d, v)`` the start of the next (cold) reduced solve."""
        z = self._z.copy()
        driven = d[self._driven]
        z[1:1 + self._nd] = driven
        z[1 + self._nd:] = self.rom.basis.T @ (x - self.rom.reference - self.rom.lift @ driven)
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
        if tuple(result.modes) == self.modes and self.rom.envelope.violation(d, v, result.modes) is None:
            self._project(np.asarray(result.positions).ravel(), d, v)
            self.resyncs += 1

    # ------------------------------------------------------------------ solve
    def solve(self, displacement: Sequence[float] | float | None = None,
              voltage: Sequence[float] | float | None = None,
              modes: Sequence[str] | None = None, check_stability: bool | None = None,
              cancel: Callable[[], bool] | None = None, force: Sequence[float] | float | None = None) -> TwinResult:
        """Move to a new command and return the state there (see :meth:`.ArrayTwin.solve`).

        Answered by the reduced model inside the envelope, by the FE otherwise
        (``result.fallback`` says why).  ``modes`` defaults to the previous ones (the
        trained modes after :meth:`reset`).  ``check_stability`` (default False)
        refreshes the reduced Hessian at the new state and reports whether it is
        positive definite.  ``cancel`` is asked between reduced Newton iterations (a
        jump or a cold start) and by an FE fallback; when it returns True the solve
        raises :class:`SolveCancelled` and the twin keeps its previous state.
        ``force`` (external forces on biased indenters [N]) only matters to an FE
        fallback: the reduced model has no biased units (a mode set with one is
        outside every envelope).

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
        tic = time.perf_counter()
        if self._resync is not None:
            self._apply_resync()
        d1 = self._command("displacement", displacement, self._displacement)
        v1 = self._command("voltage", voltage, self._voltage)
        modes = self._modes if modes is None else tuple(modes)
        code, far = classify(d1, v1, self._limit, self._bounds, self._tangent_at, self._refresh_step)
        if code == 1:
            raise ValueError(f"displacement and voltage must be finite, got {d1.tolist()} m, {v1.tolist()} V")
        if code == 2:
            raise ValueError(f"displacement {d1.tolist()} m exceeds max_displacement ({self._limit} m)")
        if code == 3 or modes != self.modes:
            modes = self.model.check_modes(modes)
            reason = self.rom.envelope.violation(d1, v1, modes) or "outside the envelope"
            return self._fallback("envelope", reason, d1, v1, modes, check_stability, cancel, tic, force=force)
        try:
            result = self._reduced(d1, v1, far, bool(check_stability), cancel, tic)
        except SolveCancelled:
            raise
        except ConvergenceError as exc:
            return self._fallback("newton", str(exc), d1, v1, modes, check_stability, cancel, tic)
        if result.error_indicator > self.tolerance:
            return self._fallback("indicator", f"error indicator {result.error_indicator:.3g} above tolerance "
                                  f"{self.tolerance:.3g}", d1, v1, modes, check_stability, cancel, tic,
                                  indicator=result.error_indicator)
        self.updates += 1
        self.last = result
        return result

    def _reduced(self, d1: np.ndarray, v1: np.ndarray, far: bool, check: bool, cancel: Callable[[], bool] | None,
                 tic: float) -> ReducedResult:
        z = self._z.copy()
        m0 = self._maxwell
        evals = refreshes = 0
        if self._cold:
            m0 = self._maxwell_factor * v1 * v1
            z[1:1 + self._nd] = d1[self._driven]
            evals, refreshes = self._settle(z, m0, self._projected, cancel)
            self._cold = self._projected = False
        else:
            refreshes = self._collect_refresh()
            if far or self._refresh_next:
                refreshes += self._request_refresh(z, m0)
        m1, result, info = np.empty(self.n_units), np.empty((5, self.n_units)), np.empty(7)
        update(self._points, z, m0, d1, v1, self._layout, self._tangent.arrays, self._cap_factor, self.second_step,
               self._buffers, m1, result, info)
        self.evaluations += int(info[4])
        evals += int(info[4])
        self._refresh_next = info[5] > 0.0
        if info[6] > self.second_step:  # a jump: the last correction still moved an output, so converge
            more, refreshed = self._settle(z, m1, True, cancel)
            update(self._points, z, m1, d1, v1, self._layout, self._tangent.arrays, self._cap_factor,
                   self.second_step, self._buffers, m1, result, info)
            self.evaluations += int(info[4])
            evals, refreshes = evals + more + int(info[4]), refreshes + refreshed
        stable = None
        if check:
            stable = self._refresh(z, m1).stable
            refreshes += 1
        self._z, self._maxwell, self._voltage, self._displacement = z, m1, v1, result[3]
        peak, sigma_min = result[4], float(info[1])
        return ReducedResult(
            displacement=result[3].copy(), voltage=v1, modes=self.modes, force=result[0], capacitance=result[1],
            delta_capacitance=result[1] - self._flat_capacitance, centre_deflection=result[2], peak_field=peak,
            energy=float(info[0]), min_principal_stress=sigma_min, wrinkled=sigma_min < 0,
            field_exceeded=bool(peak.max() > self._breakdown), stable=stable, iterations=evals,
            factorisations=refreshes, step_cuts=0, residual=float(info[3]), solve_time=time.perf_counter() - tic,
            velocity=self._zeros, bias_force=self._zeros, external_force=self._zeros, lifted_off=self._none, snaps=(),
            error_indicator=float(info[2]), recover=functools.partial(_recover, self._reference, self._vectors, z[1:]))

    def _fallback(self, kind: str, reason: str, d1: np.ndarray, v1: np.ndarray, modes: tuple,
                  check_stability: bool | None, cancel: Callable[[], bool] | None, tic: float,
                  indicator: float = math.nan, force=None) -> ReducedResult:
        """Answer with the FE; resynchronise the reduced state from it when the command is in the envelope."""
        res = self.fe.solve(d1, v1, modes, check_stability, cancel=cancel, force=force)
        self.fallbacks[kind] += 1
        self._modes, self._displacement, self._voltage = res.modes, res.displacement.copy(), v1
        if kind != "envelope":
            self._project(res.positions.ravel(), d1, v1)
        else:
            self._projected = False
        self._cold = True
        values = {f.name: getattr(res, f.name) for f in fields(TwinResult)}
        values["solve_time"] = time.perf_counter() - tic
        self.last = ReducedResult(error_indicator=indicator, fallback=f"{kind}: {reason}", **values)
        return self.last
