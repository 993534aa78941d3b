"""The protocol of ../shared/PROTOCOL.md: ring views, configurations, test and Upper views."""

import numpy as np
import pytest

from flipviz.data import DatasetError, load_builtin, make_split, observed_positions
from flipviz.data.protocol import (
    RING_INDICES,
    input_indices,
    protocol_indices,
    unobserved_indices,
    unobserved_positions,
    upper_indices,
)


def test_ring_indices_are_the_listed_ones():
    assert RING_INDICES == (0, 6, 12, 19, 25, 31, 38, 44, 50, 56, 62, 69, 75, 81, 88, 94)
    # round(k * 100 / 16): never more than half an index from the exact 22.5-degree ring
    assert np.abs(np.array(RING_INDICES) - np.arange(16) * 6.25).max() <= 0.5


def test_configurations():
    assert observed_positions(1) == list(range(8))
    assert unobserved_positions(1) == list(range(8, 16))
    assert observed_positions(8) == [14, 15, 0, 1, 2, 3, 4, 5]  # wraps around the ring
    assert unobserved_positions(8) == list(range(6, 14))
    assert input_indices(1) == [0, 6, 12, 19, 25, 31, 38, 44]
    assert unobserved_indices(1) == [50, 56, 62, 69, 75, 81, 88, 94]
    for n in range(1, 9):
        obs, tst = observed_positions(n), unobserved_positions(n)
        assert obs[0] == 2 * n - 2  # the paper's "(2n-1)th", 1-based
        assert sorted(obs + tst) == list(range(16))
        # each configuration turns the observed half by two ring positions = 45 degrees
        assert observed_positions(n % 8 + 1) == [(p + 2) % 16 for p in obs]
        ups = upper_indices(n)
        assert ups == [i + 1 for i in unobserved_indices(n)]
        assert not set(ups) & set(RING_INDICES)  # an Upper view is never a test (or input) view
        assert set(input_indices(n) + unobserved_indices(n) + ups) <= set(protocol_indices())
    assert len(protocol_indices()) == 32


@pytest.mark.parametrize("bad", [0, 9, -1, 1.5, True, "1"])
def test_bad_config_is_rejected(bad):
    with pytest.raises(ValueError, match="1..8"):
        observed_positions(bad)


def test_make_split_on_builtin():
    scene = load_builtin("mug", res=16)
    split = make_split(scene, 3)
    assert split.config == 3
    assert [v.index for v in split.inputs] == [RING_INDICES[p] for p in range(4, 12)]
    assert [v.index for v in split.tests] == [RING_INDICES[p % 16] for p in range(12, 20)]
    assert [v.index for v in split.uppers] == [v.index + 1 for v in split.tests]
    assert all(v is scene.views[v.index] for v in split.inputs + split.tests + split.uppers)
    with pytest.raises(ValueError, match="1..8"):
        make_split(scene, 9)

    del scene.views[57]  # the Upper view of test view 56
    make_split(scene, 3)  # 56 is an input of configuration 3: still fine
    with pytest.raises(DatasetError, match=r"lacks orbit views \[57\]") as e:
        make_split(scene, 1)
    assert "\n" not in str(e.value)
