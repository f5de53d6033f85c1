"""The demo material's patterns: valid, tileable, different from each other, and rendered as stacks."""
from __future__ import annotations

import numpy as np
import pytest

from btforge import stage
from btforge.errors import BtforgeInputError
from btforge.plugins.demo.patterns import make_pattern


@pytest.mark.parametrize("kind", ["stones", "plaster", "fibres", "cobbles", "gravel", "strands", "stucco", "cracks"])
def test_pattern_is_a_valid_tileable_material(kind):
    m = make_pattern(kind, 48, 40, seed=1)
    assert m.shape == (48, 40)
    assert np.isfinite(m.height).all() and m.height.std() > 0
    assert 0 < m.albedo.min() and m.albedo.max() <= 1
    # tileable: the jump across the wrap-around edge is like any other neighbour jump
    inner = np.abs(np.diff(m.height, axis=1)).mean()
    across = np.abs(m.height[:, 0] - m.height[:, -1]).mean()
    assert across < 3 * inner + 1e-6
    again = make_pattern(kind, 48, 40, seed=1)
    assert np.array_equal(m.height, again.height)


def test_patterns_differ_and_bad_names_are_clear_errors():
    kinds = ("stones", "plaster", "fibres", "cobbles", "gravel", "strands", "stucco", "cracks")
    heights = [make_pattern(k, 32, 32, seed=0).height for k in kinds]
    for i in range(len(kinds)):
        for j in range(i):
            assert not np.allclose(heights[i], heights[j]), (kinds[i], kinds[j])
    with pytest.raises(BtforgeInputError, match="stones, plaster, fibres, cobbles, gravel, strands, stucco, cracks"):
        make_pattern("bricks", 32, 32)
    with pytest.raises(BtforgeInputError, match="8 x 8"):
        make_pattern("stones", 4, 32)


def test_demo_material_renders_a_pattern_as_a_multi_light_stack():
    stack = stage("demo.material")(size=[24, 24], lights=5, pattern="stones", seed=2)["stack"]
    assert stack.samples.shape == (1, 5, 24, 24, 3)
    assert np.isfinite(stack.samples).all()
    # the relief shades differently under different lights
    assert np.abs(stack.samples[0, 0] - stack.samples[0, 1]).mean() > 1e-3
