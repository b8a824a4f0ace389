"""Scenario sets of bias design: every neighbour state up to 64 per unit, a repeatable sample above."""

import pytest

from dea_array_twin.design.scenarios import MAX_EXHAUSTIVE, scenarios


def test_all_is_every_state_of_the_other_units_for_small_arrays():
    cases = scenarios(3, [0, 1, 2])
    assert len(cases) == 3 * 2 ** 2
    assert {c.label for c in cases if c.unit == 1} == {"0s0", "0sV", "Vs0", "VsV"}
    assert all(not c.others[c.unit] and c.high[c.unit] for c in cases)


def test_above_64_states_all_samples_64_per_unit_with_the_corner_states_and_the_same_draw_every_run():
    n = 8  # 2^7 = 128 states of the other units
    cases = scenarios(n, [3])
    assert len(cases) == MAX_EXHAUSTIVE == 64
    labels = [c.label for c in cases]
    assert len(set(labels)) == 64
    assert labels[:2] == ["000s0000", "VVVsVVVV"]
    assert set(labels[2:9]) == {"".join("s" if k == 3 else ("V" if k == j else "0") for k in range(n))
                                for j in range(n) if j != 3}
    assert labels == [c.label for c in scenarios(n, [3], "all")]
    assert len(scenarios(7, [0])) == 64  # 2^6: still every state


def test_listed_states_and_errors_name_the_spec():
    cases = scenarios(3, [1], "000,101,111")
    assert [c.label for c in cases] == ["0s0", "VsV"]  # 101 and 111 are the same for unit 2
    assert [c.label for c in scenarios(3, [0, 2], "nominal")] == ["s00", "00s"]
    with pytest.raises(ValueError, match="one character per unit"):
        scenarios(3, [0], "01")
    with pytest.raises(ValueError, match="sample:N needs a whole number"):
        scenarios(3, [0], "sample:x")
