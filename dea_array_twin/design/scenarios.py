"""Operating scenarios of a bias design: which units sit at 0 V and which at V while one unit strokes.

The stroke of unit k (paper section 2) is its position at voltage V minus its position at
0 V.  In an array it depends on the other units' states (section 3.2, figures 5-6): a
*scenario* is unit k together with a state of every other unit, 0 V or V.  Its path is
the one a controller would take: from the 0 V rest state the other units' voltages are
applied (all at once, quasi-statically), giving the *low* voltage pattern; then unit k's
voltage goes from 0 to V, giving the *high* pattern.  The stroke is unit k's height in
the high pattern minus that in the low one.

Scenario sets (``--scenarios``):

* ``all`` (default): every state of the other units, ``2^(n-1)`` per unit; above
  :data:`MAX_EXHAUSTIVE` states per unit (arrays of more than 7 units) a sample of that
  many, as ``sample:64``;
* ``sample:N``: N states per unit: every other unit at 0 V, every one at V, each one
  alone at V, then states drawn at random (fixed seed, so a run is repeatable);
* ``nominal``: the other units at 0 V only (one scenario per unit);
* a list of states, e.g. ``000,101,111``: one character per unit, ``1`` (or ``V``) at
  V, ``0`` at 0 V; the stroking unit's own character is ignored.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Sequence

import numpy as np

#: A voltage pattern: per unit, whether it is at V (True) or at 0 V.
Pattern = tuple[bool, ...]

#: Above this many states of the other units per unit, ``all`` samples this many.
MAX_EXHAUSTIVE = 64
#: Seed of the random part of a sample: the same scenarios every run.
SAMPLE_SEED = 13


@dataclass(frozen=True)
class Scenario:
    """Unit ``unit`` strokes from 0 V to V while the other units hold ``others``.

    Attributes
    ----------
    unit : int
        The stroking unit, 0-based.
    others : Pattern
        Per unit whether it is at V; the entry of ``unit`` is False.
    """

    unit: int
    others: Pattern

    @property
    def low(self) -> Pattern:
        """The pattern before unit ``unit``'s voltage is applied."""
        return self.others

    @property
    def high(self) -> Pattern:
        """The pattern with unit ``unit`` at V too."""
        return tuple(True if k == self.unit else on for k, on in enumerate(self.others))

    @property
    def label(self) -> str:
        """The states as text, one character per unit: ``V``, ``0``, ``s`` for the stroking unit."""
        return "".join("s" if k == self.unit else ("V" if on else "0") for k, on in enumerate(self.others))

    @property
    def nominal(self) -> bool:
        """Every other unit at 0 V (the unit's nominal scenario)."""
        return not any(self.others)


def _states(n: int, unit: int, count: int, seed: int) -> list[Pattern]:
    """``count`` states of the units other than ``unit``: all off, all on, each alone on, then random."""
    others = [k for k in range(n) if k != unit]

    def pattern(on: Sequence[int]) -> Pattern:
        return tuple(k in on for k in range(n))

    chosen = [pattern(()), pattern(others)] + [pattern((k,)) for k in others]
    seen = set(chosen)
    out = list(dict.fromkeys(chosen))[:count]
    rng = np.random.default_rng(seed + unit)
    while len(out) < min(count, 2 ** len(others)):
        state = pattern([k for k in others if rng.random() < 0.5])
        if state not in seen:
            seen.add(state)
            out.append(state)
    return out


def scenarios(n_units: int, units: Sequence[int], spec: str = "all") -> list[Scenario]:
    """The scenarios of ``units`` (0-based) in an array of ``n_units`` for a scenario ``spec``.

    Raises
    ------
    ValueError
        A spec that is none of the forms in the module text, or a state of the wrong length.
    """
    spec = spec.strip()
    n_states = 2 ** (n_units - 1)
    out: list[Scenario] = []
    if spec == "all" and n_states > MAX_EXHAUSTIVE:
        spec = f"sample:{MAX_EXHAUSTIVE}"
    if spec == "all":
        for unit in units:
            for bits in itertools.product((False, True), repeat=n_units - 1):
                it = iter(bits)
                out.append(Scenario(unit, tuple(False if k == unit else next(it) for k in range(n_units))))
        return out
    if spec == "nominal":
        return [Scenario(unit, (False,) * n_units) for unit in units]
    if spec.startswith("sample:"):
        try:
            count = int(spec.partition(":")[2])
        except ValueError:
            count = 0
        if count < 1:
            raise ValueError(f"--scenarios sample:N needs a whole number N >= 1, got {spec!r}")
        return [Scenario(unit, state) for unit in units for state in _states(n_units, unit, count, SAMPLE_SEED)]
    states = [s.strip() for s in spec.split(",") if s.strip()]
    if not states:
        raise ValueError(f"--scenarios: expected all, nominal, sample:N or states like 000,101, got {spec!r}")
    for state in states:
        if len(state) != n_units or any(c not in "01Vvs" for c in state):
            raise ValueError(f"--scenarios: state {state!r} must have one character per unit ({n_units}), "
                             "each 0 (0 V) or 1/V (at V)")
    for unit in units:
        seen = []
        for state in states:
            pattern = tuple(k != unit and c in "1Vv" for k, c in enumerate(state))
            if pattern not in seen:
                seen.append(pattern)
                out.append(Scenario(unit, pattern))
    return out


def patterns(cases: Sequence[Scenario], n_units: int) -> list[Pattern]:
    """The rest pattern (every unit at 0 V), then the distinct low and high patterns of ``cases``."""
    rest = (False,) * n_units
    return list(dict.fromkeys([rest] + [s.low for s in cases] + [s.high for s in cases]))
