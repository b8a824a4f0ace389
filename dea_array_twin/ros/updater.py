"""The twin's solver thread: the latest command in, one update of the twin at a time, outputs out.

The node's executor only moves messages.  Its callbacks hand work to a
:class:`TwinUpdater` and return at once:

* :meth:`~TwinUpdater.post` puts a command into a one-slot mailbox per kind (sample and
  hold: a newer command of a kind replaces the older one, solved or not; with
  ``take_commands``, below, the thread posts them itself);
  :meth:`~TwinUpdater.set_modes` and :meth:`~TwinUpdater.set_config` change what the
  next update uses;
* the thread keeps its own clock: with a ``period`` it updates once per period on the
  steady clock (a timer of its own, not a ROS timer: at 500 Hz the executor's Python
  per timer callback, ~0.15 ms, was a tenth of a core taken from the solves, and the
  GIL it held delayed them); with ``period`` 0 every change of the mailbox asks for
  an update; the dynamics (``dynamics_dt``) step on the node's clock instead, one
  :meth:`~TwinUpdater.tick` per period (``use_sim_time`` honoured);
* :meth:`~TwinUpdater.reset` pre-empts: a running solve is abandoned at its next Newton
  iteration, the twin returns to the flat state at 0 m, 0 V and the callback is told.

With ``take_commands`` (quasi-static updates with a ``period``: what the node does) the
commands are not handed over by the executor at all: at every tick the thread first calls
``take_commands()``, which takes the latest message of each command subscription and
posts it.  At 500-1000 commands a second, the executor's wake-up, wait-set rebuild and
callback per message (about 0.2-0.3 of a core in Python, holding the GIL the solver
thread needs between its compiled kernels) cost more ticks than they save latency: a
command is used at the next tick either way.

The thread takes a :class:`CommandSnapshot` of the mailbox, makes one call into the
twin (:meth:`_update_twin`, the only place that touches the
:class:`~dea_array_twin.model.twin.ArrayTwin`, which is not thread-safe) and hands the
result to ``publish``.  A solve has a time budget: past it, if a newer command waits in
the mailbox, the solve is abandoned at its next Newton iteration
(:class:`~dea_array_twin.model.solver.SolveCancelled`), the last good state is kept and
published, the overrun is counted, and the newest command is taken next.  Two rules
keep the twin making progress:

* a solve past its budget with nothing newer to do runs on (abandoning it would
  only throw its work away: a single step command, a change of unit modes, always gets
  its answer, however long it takes; ``reset`` still pre-empts it);
* each consecutive abandonment doubles the budget of the next solve (back to
  ``budget`` after a solve that ends, well or not): a stream of commands that each need
  longer than the budget (a change of unit modes, a big jump under way) is not starved
  for ever, it is answered within about twice its solve time.

With ``dynamics_dt`` (biased units with a moving mass) every tick advances the twin's
dynamics: one :meth:`~dea_array_twin.model.twin.ArrayTwin.step` of ``dynamics_dt`` times
the ticks since the last step (1 unless the thread fell behind, which is counted as
skipped ticks), with the commands the mailbox held at the tick (taken in :meth:`tick`, so
a command counts for the step of the first tick after it arrived), new or not, from the
quasi-static equilibrium the first update after start or ``reset`` solves; the result
is published with the tick's time stamp.  Otherwise an update is a
quasi-static solve, made only when a command changed.

Counters, rates and solve-time percentiles for the node's diagnostics come from
:meth:`~TwinUpdater.stats`.  No rclpy here: the node passes plain callables.
"""

from __future__ import annotations

import functools
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from ..model.config import ArrayConfig
from ..model.solver import ConvergenceError, SolveCancelled
from ..model.twin import BIASED, ArrayTwin, TwinResult

#: Seconds of solves the solve-time percentiles are taken over.
STATS_WINDOW = 10.0
#: Seconds the update and output rates are averaged over.
RATE_WINDOW = 5.0


@dataclass(frozen=True)
class CommandSnapshot:
    """Everything one update of the twin needs, taken from the mailbox at once.

    Attributes
    ----------
    commands : mapping of str to ndarray
        Command kind -> one value per unit, SI units; the kinds are the keyword
        arguments of :meth:`ArrayTwin.solve` (``displacement`` [m], ``voltage`` [V],
        ``force`` [N]).
    modes : tuple of str
        ``"driven"`` / ``"free"`` per unit.
    config : ArrayConfig
        The config with the run-time parameters now in force.
    seq : int
        Increases with every change of the mailbox.
    ticks : int
        Update periods this update covers (a dynamic step advances by that many ``dt``).
    stamp_ns : int or None
        Clock time of the tick a dynamic step ends at [ns].
    """

    commands: Mapping[str, np.ndarray]
    modes: tuple[str, ...]
    config: ArrayConfig
    seq: int
    ticks: int = 1
    stamp_ns: int | None = None


@dataclass
class UpdaterStats:
    """What the solver thread did (for diagnostics); counts since start unless said otherwise.

    ``updates_per_s`` (successful solves) and ``outputs_per_s`` are averages over the
    last :data:`RATE_WINDOW` seconds; the solve times [s] are those of the successful
    solves of the last :data:`STATS_WINDOW` seconds (nan if none).
    """

    updates: int = 0
    failed_solves: int = 0
    budget_overruns: int = 0
    skipped_ticks: int = 0
    snaps: int = 0
    lift_offs: int = 0
    outputs: int = 0
    updates_per_s: float = 0.0
    outputs_per_s: float = 0.0
    solve_time_p50: float = float("nan")
    solve_time_p95: float = float("nan")
    solve_time_max: float = float("nan")
    last_error: str = ""
    thread_error: str = ""
    #: The verdict of the last stability check (None: none yet, or no inertia) and how long ago the state it
    #: judged was solved [s] (inf: none yet).
    stable: bool | None = None
    stability_age: float = float("inf")


class TwinUpdater:
    """Runs every solve of ``twin`` on its own thread, on the latest command.

    Parameters
    ----------
    twin : ArrayTwin
        Touched only by this thread from :meth:`start` on.
    commands : mapping of str to array
        The initial command of each kind (usually zeros).
    modes : sequence of str
        Initial unit modes.
    publish : callable
        ``publish(result)`` after every update (on this thread), with the last good
        result (also after a failed or abandoned solve).
    log : callable
        ``log(key, text)`` for warnings (throttling is the caller's business).
    budget : float
        Seconds a solve may take before it is abandoned for a newer command; 0 = no budget.
    stability_period : float
        Seconds between stability checks of the equilibrium (0 = every update).
    period : float
        Seconds between updates on the steady clock (``1 / update_rate``); 0 = update on
        every change of the mailbox.  A period that passes while a solve runs is counted
        in ``skipped_ticks``; the schedule keeps its phase (as a ROS timer does).
    dynamics_dt : float, optional
        Time step [s] of the dynamics, advanced at every :meth:`tick` (which then paces
        the updates instead of ``period``); None: quasi-static updates.
    take_commands : callable, optional
        Called on this thread at every tick, before the mailbox is read, and by a solve
        past its budget (is a newer command waiting?): it takes the latest commands from
        wherever they wait and posts them (:meth:`post`).  Quasi-static
        updates with a ``period`` only (otherwise commands wake the thread, or a tick
        holds the commands it saw, and they must be posted as they come).
    background_checks : bool
        Check stability in the twin's worker thread
        (:meth:`~dea_array_twin.model.twin.ArrayTwin.check_in_background`,
        :meth:`~dea_array_twin.model.reduced_twin.ReducedTwin.check_in_background`) after an
        unchecked update instead of in the update itself, unless a unit is biased (its
        check needs the bordered tangent: the update checks itself); an update whose state
        the twin cannot check there after all has the next update checked in it.
    """

    def __init__(self, twin: ArrayTwin, commands: Mapping[str, Sequence[float]], modes: Sequence[str],
                 publish: Callable[[TwinResult], None], log: Callable[[str, str], None], budget: float,
                 stability_period: float, period: float = 0.0, dynamics_dt: float | None = None,
                 take_commands: Callable[[], None] | None = None, background_checks: bool = False):
        if take_commands is not None and (period <= 0 or dynamics_dt is not None):
            raise ValueError("take_commands needs quasi-static updates with a period > 0")
        self.twin = twin
        self._take_commands = take_commands
        self.dynamics_dt = dynamics_dt
        self._tick: tuple | None = None  # (commands, stamp) at the last tick, for dynamics
        self._result_stamp: int | None = None  # tick stamp of the last good dynamic step
        self._publish, self._log = publish, log
        self.budget, self.stability_period, self.period = budget, stability_period, period
        self._cond = threading.Condition()
        self._commands = {kind: np.array(v, dtype=float) for kind, v in commands.items()}
        self._modes = tuple(modes)
        self._config = twin.config
        self._seq, self._solved_seq = 1, 0  # the first update solves the initial command ...
        self._next_tick = -np.inf  # ... at once (then every period from start)
        self._ticks = 0 if dynamics_dt is None else 1  # periods passed since the last update (ticked: first at once)
        self._resets: list[Callable[[bool, str], None]] = []
        self._stopping = False
        self._last_stability = -np.inf
        self.background_checks = background_checks
        self._check_here = False  # the twin could not check in the background: the next update checks itself
        self._resets_done = 0  # a background verdict started before a reset is of a state no longer held
        self._abandoned_in_a_row = 0
        #: The last good result (None until the first solve succeeds); read by the node's timers.
        self.result: TwinResult | None = None
        self._stats = UpdaterStats()
        self._checked_at: float | None = None  # when the state of the last stability verdict was solved
        self._solve_times: deque[tuple[float, float]] = deque()  # (end, duration) of recent solves
        self._output_times: deque[float] = deque()
        self._started = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="twin-solver", daemon=True)

    # ------------------------------------------------------------------ called from the executor
    def start(self) -> None:
        """Start the thread (it makes the first update at once)."""
        self._thread.start()

    def post(self, kind: str, values: Sequence[float]) -> None:
        """Hold ``values`` as the latest command of ``kind`` (checked by the caller)."""
        with self._cond:
            self._commands[kind] = np.array(values, dtype=float)
            self._changed()

    def held(self, kind: str) -> np.ndarray:
        """The command of ``kind`` in the mailbox now (what the next update uses)."""
        with self._cond:
            return self._commands[kind].copy()

    def set_modes(self, modes: Sequence[str]) -> None:
        """Use ``modes`` from the next update on (checked by the caller)."""
        with self._cond:
            self._modes = tuple(modes)
            self._changed()

    def set_config(self, config: ArrayConfig) -> None:
        """Use ``config`` (run-time fields changed only) from the next update on."""
        with self._cond:
            self._config = config
            self._changed()

    def tick(self, stamp_ns: int | None = None) -> None:
        """One update period has passed (at clock time ``stamp_ns``, for dynamics)."""
        with self._cond:
            self._ticks += 1
            if self.dynamics_dt is not None:
                self._tick = ({k: v.copy() for k, v in self._commands.items()}, stamp_ns)
            self._cond.notify()

    def reset(self, done: Callable[[bool, str], None]) -> None:
        """Abandon any running solve, return to 0 m, 0 V and the flat state; then call ``done(ok, message)``."""
        with self._cond:
            self._resets.append(done)
            self._cond.notify()

    def stop(self, timeout: float = 10.0) -> None:
        """Abandon any running solve and end the thread (no update or publish after this returns)."""
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)
            if self._thread.is_alive():
                self._log("stop", f"the solver thread is still busy {timeout} s after the stop; leaving it")

    def stats(self) -> UpdaterStats:
        """Counters, rates and solve-time percentiles (see :class:`UpdaterStats`)."""
        now = time.monotonic()
        with self._cond:
            s = UpdaterStats(**vars(self._stats))
            if self._checked_at is not None:
                s.stability_age = now - self._checked_at
            self._prune(now)
            ends = np.array([end for end, _ in self._solve_times])
            times = np.array([dt for _, dt in self._solve_times])
            outputs = len(self._output_times)
        span = max(min(RATE_WINDOW, now - self._started), 1e-3)
        s.updates_per_s, s.outputs_per_s = np.count_nonzero(ends >= now - RATE_WINDOW) / span, outputs / span
        if times.size:
            s.solve_time_p50, s.solve_time_p95 = np.percentile(times, [50, 95])
            s.solve_time_max = times.max()
        return s

    def _prune(self, now: float) -> None:
        while self._solve_times and self._solve_times[0][0] < now - STATS_WINDOW:
            self._solve_times.popleft()
        while self._output_times and self._output_times[0] < now - RATE_WINDOW:
            self._output_times.popleft()

    def _changed(self) -> None:
        self._seq += 1
        if self.period <= 0 and self.dynamics_dt is None:
            self._cond.notify()

    # ------------------------------------------------------------------ the thread
    def _wait_until_due(self) -> None:
        """Wait (holding ``_cond``) for the next tick (own clock or :meth:`tick`), a change of the
        mailbox (no period), a reset or stop; ``_ticks`` counts the periods that passed."""
        while not (self._stopping or self._resets):
            if self.dynamics_dt is not None or self.period <= 0:
                if self._ticks > 0 if self.dynamics_dt is not None else self._seq != self._solved_seq:
                    return
                self._cond.wait()
                continue
            now = time.monotonic()
            if now >= self._next_tick:
                if self._next_tick == -np.inf:  # the first update: the schedule starts now
                    self._next_tick = now
                missed = int((now - self._next_tick) / self.period)  # periods a solve outlasted
                self._ticks += 1 + missed
                self._next_tick += (missed + 1) * self.period
                return
            self._cond.wait(self._next_tick - now)

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    self._wait_until_due()
                    if self._stopping:
                        return
                if self._take_commands is not None:
                    self._take_commands()
                with self._cond:
                    resets, self._resets = self._resets, []
                    if resets:
                        for kind in self._commands:
                            self._commands[kind] = np.zeros_like(self._commands[kind])
                        self._seq += 1
                    elif self._ticks > 1:  # ticks that passed while the last solve ran
                        self._stats.skipped_ticks += self._ticks - 1
                    ticks, self._ticks = self._ticks, 0
                    snapshot = None
                    if self.dynamics_dt is not None and ticks and not resets and self._tick is not None:
                        commands, stamp = self._tick  # what the mailbox held at the tick
                        snapshot = CommandSnapshot(commands, self._modes, self._config, self._seq, ticks, stamp)
                        self._solved_seq = self._seq
                    elif self._seq != self._solved_seq:
                        snapshot = CommandSnapshot({k: v.copy() for k, v in self._commands.items()}, self._modes,
                                                   self._config, self._seq, max(ticks, 1))
                        self._solved_seq = self._seq
                if resets:
                    self.twin.reset()
                    self._last_stability = -np.inf
                    with self._cond:
                        self._resets_done += 1
                        self._stats.stable, self._stats.stability_age = None, float("inf")
                        self._checked_at = None
                if snapshot is not None:
                    self._solve(snapshot)
                for done in resets:
                    error = self._stats.last_error
                    done(not error, "twin reset to 0 m, 0 V" if not error else error)
                if self.result is not None and not self._stopping:
                    if self._result_stamp is None:
                        self._publish(self.result)
                    else:  # a dynamic step: the state at its tick
                        self._publish(self.result, self._result_stamp)
                    with self._cond:
                        self._stats.outputs += 1
                        self._output_times.append(time.monotonic())
                        self._prune(time.monotonic())
        except Exception as exc:  # noqa: BLE001 - reported in diagnostics, never silent
            with self._cond:
                self._stats.thread_error = f"solver thread stopped: {exc!r}"
            self._log("thread", self._stats.thread_error)

    def _solve(self, snapshot: CommandSnapshot) -> None:
        start = time.monotonic()
        budget = self.budget * 2 ** self._abandoned_in_a_row
        deadline = start + budget if self.budget > 0 else np.inf
        check = start - self._last_stability >= self.stability_period
        in_background = check and self.background_checks and not self._check_here and BIASED not in snapshot.modes

        def cancel() -> bool:
            if self._stopping or self._resets:
                return True
            if time.monotonic() <= deadline:
                return False
            if self._take_commands is not None:  # past the budget: is a newer command waiting?
                self._take_commands()
            return self._seq != snapshot.seq

        try:
            result = self._update_twin(snapshot, check and not in_background, cancel)
        except SolveCancelled:
            if self._stopping or self._resets:
                self._abandoned_in_a_row = 0
                return  # pre-empted: no verdict on the command
            self._abandoned_in_a_row += 1
            text = (f"solve abandoned after {time.monotonic() - start:.3g} s, past its budget of {budget:.3g} s "
                    f"(solve_budget), for a newer command; keeping the last state")
            with self._cond:
                self._stats.budget_overruns += 1
                self._stats.last_error = text
            self._log("budget", text)
            return
        except (ConvergenceError, ValueError) as exc:
            self._abandoned_in_a_row = 0
            with self._cond:
                self._stats.failed_solves += 1
                self._stats.last_error = str(exc)
            self._log("solve", f"solve failed, keeping the last state: {exc}")
            return
        now = time.monotonic()
        self._abandoned_in_a_row = 0
        if in_background:
            verdict = self.twin.check_in_background()
            self._check_here = verdict is None
            if verdict is not None:
                self._last_stability = start
                verdict.add_done_callback(functools.partial(self._judged, now, self._resets_done))
        elif check:
            self._last_stability = start
            self._check_here = False
            with self._cond:
                self._stats.stable, self._checked_at = getattr(result, "stable", None), now
        # Snap-throughs and new lift-offs, for diagnostics (a result without them counts none).
        lifted = np.asarray(getattr(result, "lifted_off", ()), dtype=bool)
        before = np.asarray(getattr(self.result, "lifted_off", np.zeros_like(lifted)), dtype=bool)
        self.result = result
        self._result_stamp = snapshot.stamp_ns
        with self._cond:
            self._stats.snaps += len(getattr(result, "snaps", ()))
            self._stats.lift_offs += int(np.count_nonzero(lifted & ~before)) if before.shape == lifted.shape else 0
            self._stats.updates += 1
            self._stats.last_error = ""
            self._solve_times.append((now, now - start))

    def _judged(self, solved: float, resets: int, verdict: Future) -> None:
        """A background stability check of the state solved at ``solved`` (monotonic) is done (worker thread)."""
        with self._cond:
            if resets != self._resets_done or (self._checked_at is not None and self._checked_at > solved):
                return  # of a state before a reset, or older than the verdict held
            if verdict.exception() is not None:
                self._stats.stable, self._checked_at = None, solved
                text = f"background stability check failed: {verdict.exception()!r}"
            else:
                self._stats.stable, self._checked_at = verdict.result(), solved
                return
        self._log("stability", text)

    def _update_twin(self, snapshot: CommandSnapshot, check_stability: bool,
                     cancel: Callable[[], bool]) -> TwinResult:
        """The one call into the twin per update (a new command kind is one more keyword).

        Dynamics start from the quasi-static equilibrium: the first update after start or
        ``reset`` is a solve, the next ones are time steps."""
        self.twin.config = snapshot.config
        if self.dynamics_dt is not None and self.twin.last is not None:
            return self.twin.step(self.dynamics_dt * snapshot.ticks, modes=snapshot.modes,
                                  check_stability=check_stability, cancel=cancel, **snapshot.commands)
        return self.twin.solve(modes=snapshot.modes, check_stability=check_stability, cancel=cancel,
                               **snapshot.commands)
