"""Helper threads sharing a reduced update's evaluations (model/point_team.py, the chunked passes of
model/rom_kernels.py): the same outputs to the bit whoever evaluates which chunk, a stalled helper's
chunk taken over by the caller, and a twin whose helper thread joins its updates."""

import time

import numpy as np
import pytest
from conftest import coarse_point_maps

from dea_array_twin.model import rom_kernels as rk
from dea_array_twin.model.point_team import MAX_THREADS, PointTeam
from dea_array_twin.model.reduced_twin import TEAM_BYTES, ReducedTwin


@pytest.fixture(scope="module")
def points():
    """Maps of 300 quadrature points of the coarse array (5 chunks, the last one short; 4 monitor points,
    a tenth held) as an update's ``points`` tuple."""
    model, fmap, wmap, xi, unit = coarse_point_maps(300, 7)
    xi[[0, 70, 130, 299]] = 0.0
    held = np.random.default_rng(8).random(xi.size) < 0.1
    y = model.yeoh
    return fmap, wmap, xi, unit, held, y.c10, y.c20, y.c30


def _passes(points, team, kinds, single, split):
    """Run ``kinds`` as the caller of ``team`` after ``split(points, team, generation, kind)`` has played the
    helpers."""
    fmap, wmap = points[0], points[1]
    z = np.array([1.0, 0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.2])
    maxwell = np.array([2e4, 3e4, 0.0])
    out = (np.empty(fmap.shape[2]), np.empty(3), np.empty(wmap.shape[2]), np.empty(3))
    control, state = team[0], team[1]
    results = []
    for kind in kinds:
        generation = rk._publish(control, state, *team[5:], kind, single, z, maxwell)
        split(points, team, generation, kind)
        rk._claims(*points, *team, 0)
        energy, sigma = rk._finish(*points, *team, generation, kind, *out)
        results.append((energy, sigma, *(a.copy() for a in out)))
    return results


def _alone(points, team, generation, kind):
    """No helper."""


def _helper_first(points, team, generation, kind):
    """Helper 1 claims every chunk before the caller starts."""
    rk._claims(*points, *team, 1)


def _every_other(points, team, generation, kind):
    """Helper 2 has finished the even chunks."""
    state = team[1]
    for k in range(0, state.size, 2):
        rk._run_chunk(*points, *team, kind, k, 2)
        state[k] = 16 * generation + rk._FINISHED + 2


def _stalled(points, team, generation, kind):
    """Helper 1 claimed chunks 1 and 3 and never finishes them."""
    team[1][[1, 3]] = 16 * generation + rk._CLAIMED + 1


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_any_split_of_the_chunks_between_threads_gives_the_same_outputs_to_the_bit(points, dtype):
    """Each chunk's sums are its own, added in chunk order by the caller: a pass gives the same energy,
    gradient, gradient along W, electrode integrals, largest det C and smallest stress to the last bit
    whether the caller evaluated every chunk, a helper evaluated all, every other one, or claimed two and
    stalled (the caller waits ``control[_WAIT]`` spins, then evaluates them itself and counts them)."""
    points = tuple(a.astype(dtype) if i < 2 else a for i, a in enumerate(points))
    single = dtype == np.float32
    kinds = (rk._GRADIENT_DEFER, rk._ENRICHMENT, rk._GRADIENT)
    fmap, wmap, xi = points[0], points[1], points[2]
    runs = {}
    for name, split in (("alone", _alone), ("helper first", _helper_first), ("every other", _every_other),
                        ("stalled", _stalled)):
        team = rk.team_arrays(3, xi.size, fmap.shape[2], wmap.shape[2], 3)
        team[0][rk._WAIT] = 1000
        runs[name] = (_passes(points, team, kinds, single, split), team[0].copy())
    reference, _ = runs.pop("alone")
    assert reference[0][2].any() and reference[1][4].any() and reference[2][4].any()  # gradients, and along W
    np.testing.assert_allclose(reference[1][4], reference[2][4], rtol=1e-12)  # deferred W = direct W
    for name, (results, control) in runs.items():
        for got, want in zip(results, reference):
            for a, b in zip(got, want):
                assert np.array_equal(a, b), name
    assert runs["helper first"][1][rk._HELPED] == 3 * 5
    assert runs["stalled"][1][rk._TAKEN] == 3 * 2


def test_a_team_checks_its_size_and_the_twin_shares_only_large_rom_updates(coarse_rom, points):
    """1 to MAX_THREADS threads; ``threads=None`` keeps a ROM whose maps are under TEAM_BYTES (the coarse
    test ROM's, a few kB) to the calling thread."""
    for n in (0, MAX_THREADS + 1):
        with pytest.raises(ValueError, match="threads"):
            PointTeam(points, n, 3)
    cfg, rom, _, _ = coarse_rom
    twin = ReducedTwin(cfg, rom)
    assert twin.threads == 1 and twin._fmap.nbytes + twin._wmap.nbytes < TEAM_BYTES
    twin.close()


def test_a_twin_with_a_helper_thread_answers_as_with_one_and_stops_it_on_close(coarse_rom):
    """Warm updates along a path (every indenter and voltage moving) give bit-identical outputs with a
    helper thread and without; the helper takes chunks of them (updates are repeated until it has, at
    most 20 s: it runs at the lowest priority); close() ends its thread."""
    cfg, rom, _, _ = coarse_rom
    alone, team = ReducedTwin(cfg, rom, threads=1), ReducedTwin(cfg, rom, threads=2)
    assert team.threads == 2 and team.team.wait > 0
    t = np.linspace(0.0, 1.0, 60)
    d = 4e-3 + 2e-3 * np.sin(2 * np.pi * t[:, None] + np.arange(3))
    v = np.column_stack([np.zeros_like(t), 1500 + 500 * np.sin(2 * np.pi * t), 1200 + 600 * np.cos(2 * np.pi * t)])
    for k in range(t.size):
        a, b = alone.solve(d[k], v[k]), team.solve(d[k], v[k])
        assert a.fallback == b.fallback == ""
        for name in ("force", "capacitance", "centre_deflection", "peak_field"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.energy == b.energy and a.error_indicator == b.error_indicator
    end = time.monotonic() + 20.0
    k = 0
    while team.team.helped == 0 and time.monotonic() < end:
        team.solve(d[k % t.size], v[k % t.size])
        k += 1
    assert team.team.helped > 0
    threads = list(team.team._threads)
    assert all(thread.is_alive() for thread in threads)
    team.close()
    alone.close()
    for thread in threads:
        thread.join(timeout=5.0)
        assert not thread.is_alive()
