"""The tiled map's bases by their grid: the Hilbert tiles (casmag.gp.tiles) or the bump
lattice (casmag.gp.bumps), one object per grid and process."""

from __future__ import annotations

from functools import lru_cache

from casmag.gp.bumps import BumpBasis, is_bump_grid
from casmag.gp.tiles import TiledBasis, TileGrid


@lru_cache(maxsize=8)
def cached_tiles(grid: TileGrid) -> TiledBasis:
    """The basis of a grid: a :class:`casmag.gp.bumps.BumpBasis` for a bump lattice, a
    :class:`casmag.gp.tiles.TiledBasis` otherwise; built once per process."""
    return BumpBasis(grid) if is_bump_grid(grid) else TiledBasis(grid)
