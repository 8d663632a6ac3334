"""Checks of the field models (casmag.model.field) that need no solve."""

import numpy as np

from casmag.model.field import left_map_box


def test_positions_beyond_the_map_box_are_flagged_with_the_evidence():
    """The reduced-rank map is the GP model only inside its box: positions beyond any face
    raise ``left_map_box``, with how many and how far; positions inside (or on a face) do
    not. Planar positions are checked against the first two axes of a 3-D box."""
    center, half = (0.0, 1.0, 0.5), (1.0, 2.0, 0.3)
    inside = np.array([[0.9, -0.9, 0.5], [-1.0, 3.0, 0.2], [0.0, 1.0, 0.8]])
    assert left_map_box(center, half, inside) is None
    outside = np.vstack([inside, [[1.25, 1.0, 0.5], [0.0, -1.5, 0.5]]])
    flag = left_map_box(center, half, outside)
    assert flag["name"] == "left_map_box"
    assert flag["evidence"]["positions_outside"] == 2
    assert flag["evidence"]["positions"] == 5
    assert np.isclose(flag["evidence"]["max_beyond_m"], 0.5)  # y: |-1.5 - 1| - 2
    assert "2 of 5" in flag["reason"] and "\n" not in flag["reason"]
    planar = np.array([[0.5, 1.0], [0.0, 3.2]])
    assert left_map_box(center, half, planar)["evidence"]["positions_outside"] == 1
