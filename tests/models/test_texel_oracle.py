"""models.texel_oracle: per-texel means with coarse fallback."""

from __future__ import annotations

import numpy as np
import pytest

from deliffas.models.texel_oracle import TexelMeans, texel_index


def test_texel_index_follows_the_atlas_convention():
    # texel (row 0, col 0) is the top-left: u small, v near 1
    assert texel_index(np.array([[0.01, 0.99], [0.99, 0.01], [1.0, 0.0]]), 4).tolist() == [0, 15, 15]


def test_means_and_the_coarse_fallback():
    tm = TexelMeans(sides=(2, 4))
    uv = np.array([[0.1, 0.9], [0.1, 0.9], [0.3, 0.7]])  # the same 4x4 texel twice, a neighbour once
    tm.add(uv, np.array([[1.0, 0, 0], [0.0, 0, 0], [0.0, 1, 0]]))
    np.testing.assert_allclose(tm.lookup(uv[:1], 4), [[0.5, 0, 0]])
    # a texel no ray met at side 4 takes the 2x2 texel it lies in (all three rays: mean)
    np.testing.assert_allclose(tm.lookup(np.array([[0.45, 0.95]]), 4), [[1 / 3, 1 / 3, 0]])
    assert tm.lookup(np.array([[0.9, 0.1]]), 4).tolist() == [[0.0, 0.0, 0.0]]  # nothing anywhere
    assert tm.coverage(4) == pytest.approx(2 / 16)
    with pytest.raises(ValueError, match="not one of"):
        tm.lookup(uv, 8)
