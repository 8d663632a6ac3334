"""A field map saved to a file, to draw and to localise a later recording against.

Every GP-SLAM run with a reduced-rank box map (the translational, planar, pose and IMU
models, one recording or several sessions) writes ``map.npz`` beside ``result.json``: the
Hilbert basis (kernel, box centre and half width [m], number of functions), the dimension
of the positions it is read at, the hyperparameters it was solved with, and the posterior
of the map's unknowns z = [vec(W); c] (the weights W, column-major, then the constant field
c when the model has one) as a mean and a precision matrix. A run with the tiled map
(casmag.gp.tiles: the translational, planar and pose models) writes the same posterior of
its tiles' weights (each tile's functions, tile after tile) and constant field, with the
tile grid in place of the box (spacing, origin, tile indices, the tiles' basis; format
:data:`TILED_FORMAT`; the precision stored as its upper triangle, ``precision_upper``,
half the size of a dense one); it is drawn as a box map is and locates a translational,
planar or pose recording (casmag.solver.localize, casmag.solver.staged.PriorMap); the
filter needs a box (:meth:`SavedMap.require_box`). A map with more unknowns than a run
saves a precision for (casmag.solver.uncertainty.MAP_MAX_UNKNOWNS: a dense matrix) is
saved as its mean alone (``mean_only``): it is drawn (its standard deviation NaN), and
cannot locate a recording (:meth:`SavedMap.require_posterior`). The map is the field in
the map frame, m(p) + c, whatever the motion model: the planar, pose and IMU models read it
through the body's rotation and solve for whitened weights, which are turned into W before
it is saved. The precision is the Laplace approximation at the MAP, marginal over the
path: the inverse of the z block of the inverse Hessian of the whole objective
(casmag.nlp.NLP.hessian), so the uncertainty of the positions the map was made from is in
it, not taken as known. Hyperparameters are taken as known.

The map is in the frame of the run that made it: the first true pose of a recording with
truth (``casmag slam``'s default anchor), else the origin of the odometry. A recording
localised against the map (:mod:`casmag.solver.localize`) must start in that frame.

Field units are the magnetometer's; positions metres. ``casmag map MAP --out DIR`` draws
the mean and the standard deviation of the field on a grid and writes the grid as CSV.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps

from casmag.errors import DataError
from casmag.gp.fieldmap import GRID_POINTS, chunks, weight_rows
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.localmaps import cached_tiles
from casmag.gp.reduced_rank import HilbertBasis, cached_basis
from casmag.gp.tiles import TiledBasis, TileGrid
from casmag.linalg import dense_product

#: The file name every run writes its map to.
MAP_FILE = "map.npz"

#: Format version written into the file of a box map (bumped when a field changes meaning).
FORMAT = 1

#: The format of a tiled map's file: a box map's fields (``center`` and ``half_width`` the
#: tile centres' bounding box, ``num_basis`` the functions per tile) and the tile grid's.
TILED_FORMAT = 2

_TILE_FIELDS = ("tiles_spacing", "tiles_origin", "tiles_index", "tiles_basis")

KERNELS = ("se", "curl_free")

_FIELDS = (
    "format",
    "kernel",
    "center",
    "half_width",
    "num_basis",
    "sigma_f",
    "lengthscale",
    "sigma_m",
    "constant_field",
    "mean",
    "precision",
    "frame",
)


@dataclass(frozen=True, eq=False)
class SavedMap:
    """A reduced-rank field map with its posterior (module docstring).

    kernel: ``se`` or ``curl_free``; center, half_width: the basis box (d,) [m], d = 2 or 3;
    position_dim: the positions it is read at (default d; 2 for a curl-free map of planar
    positions, whose potential lives on a 3-D box and is read at z = 0);
    num_basis: M; sigma_f, lengthscale [m], sigma_m: the hyperparameters it was solved
    with (field units but the lengthscale); constant_field: z ends with c (3,); mean (n_z,),
    precision (n_z, n_z): the posterior of z (None: the mean alone was saved, the map too
    large for a dense precision); frame: what its origin is. ``tiles``: a tiled
    map's grid (casmag.gp.tiles, curl-free; :func:`tiled_map`), whose weights are each
    tile's functions tile after tile; center and half_width are then the box of its tile
    centres, num_basis the functions per tile."""

    kernel: str
    center: tuple[float, ...]
    half_width: tuple[float, ...]
    num_basis: int
    sigma_f: float
    lengthscale: float
    sigma_m: float
    constant_field: bool
    mean: np.ndarray
    precision: np.ndarray | None
    frame: str = ""
    position_dim: int | None = None
    tiles: TileGrid | None = None

    def __post_init__(self) -> None:
        if self.position_dim is None:
            object.__setattr__(self, "position_dim", len(self.center))
        if not 2 <= int(self.position_dim) <= len(self.center):
            raise ValueError(
                f"position_dim {self.position_dim} is not 2..{len(self.center)} (the box's)"
            )
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel {self.kernel!r} is not one of {', '.join(KERNELS)}")
        if self.tiles is not None:
            if self.kernel != "curl_free":
                raise ValueError(f"a tiled map is curl-free, not {self.kernel!r}")
            if self.tiles.dim != self.position_dim:
                raise ValueError(
                    f"tiles over {self.tiles.dim} axes read at {self.position_dim}-D positions"
                )
            if self.tiled_basis().per_tile != self.num_basis:
                raise ValueError(
                    f"num_basis {self.num_basis}: the tiles have "
                    f"{self.tiled_basis().per_tile} functions each"
                )
        n_z = self.size
        shape = None if self.precision is None else self.precision.shape
        if self.mean.shape != (n_z,) or shape not in (None, (n_z, n_z)):
            raise ValueError(
                f"mean {self.mean.shape} and precision {shape} do not fit {n_z} unknowns"
            )

    @property
    def dim(self) -> int:
        """Dimension of the positions (2 or 3)."""
        return int(self.position_dim)

    @property
    def form(self) -> str:
        """``tiled`` or ``reduced_rank`` (one box)."""
        return "reduced_rank" if self.tiles is None else "tiled"

    def require_box(self, where: str, what: str = "locate a recording") -> None:
        """Raise DataError naming ``where`` (the map's file) when the map is tiled: only a
        box map can ``what`` yet."""
        if self.tiles is not None:
            raise DataError(
                f"{where or 'map'}: a tiled map ({self.tiled_basis().num_tiles} tiles); only "
                f"a map of one box can {what} (casmag map draws this one)"
            )

    @property
    def has_posterior(self) -> bool:
        """Whether the precision was saved (else the mean alone: ``mean_only``)."""
        return self.precision is not None

    def require_posterior(self, where: str, what: str = "locate a recording") -> None:
        """Raise DataError naming ``where`` (the map's file) when the map was saved as its
        mean alone: ``what`` needs its uncertainty."""
        if self.precision is None:
            raise DataError(
                f"{where or 'map'}: saved as its mean alone ({self.size:,} unknowns, too many "
                f"for a dense precision), so it cannot {what} (casmag map draws its mean)"
            )

    @property
    def basis_key(self) -> tuple:
        """(center, half_width, num_basis): the key of casmag.gp.reduced_rank.cached_basis."""
        return (tuple(self.center), tuple(self.half_width), int(self.num_basis))

    @property
    def num_weights(self) -> int:
        if self.tiles is not None:
            return self.tiled_basis().num_weights
        return self.num_basis * (FIELD_DIM if self.kernel == "se" else 1)

    @property
    def size(self) -> int:
        """Number of unknowns z: the weights and, with a constant field, c."""
        return self.num_weights + (FIELD_DIM if self.constant_field else 0)

    def basis(self) -> HilbertBasis:
        self.require_box("map", "give one basis")
        return cached_basis(self.basis_key)

    def tiled_basis(self) -> TiledBasis:
        assert self.tiles is not None, "a box map has no tiles"
        return cached_tiles(self.tiles)

    def hyperparameters(self) -> dict[str, float]:
        return {"sigma_f": self.sigma_f, "lengthscale": self.lengthscale, "sigma_m": self.sigma_m}

    def unknowns(self, z: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """``W`` (M, 3) (SE), (M, 1) (curl-free) or, tiled, (m, T) (each tile's m functions
        a column) and, with a constant field, ``c`` (3, 1), from z (default: the mean)."""
        z = self.mean if z is None else np.ravel(z)
        if self.tiles is not None:
            shape = (self.num_basis, self.tiled_basis().num_tiles)
        else:
            shape = (self.num_basis, FIELD_DIM if self.kernel == "se" else 1)
        out = {"W": z[: self.num_weights].reshape(shape, order="F")}
        if self.constant_field:
            out["c"] = z[self.num_weights :].reshape(FIELD_DIM, 1)
        return out

    def design(self, X: np.ndarray) -> list[Any]:
        """Per field component q, the (n, n_z) rows d m_q(X) / d z at points X (n, d):
        dense for a box, scipy CSR for tiles."""
        X = self._points(X)
        n_w = self.num_weights
        if self.tiles is not None:
            A = self.tiled_basis().design(X)  # (3 n, n_w), component-major
            n = X.shape[0]
            out = []
            for q in range(FIELD_DIM):
                blocks = [A[q * n : (q + 1) * n]]
                if self.constant_field:
                    e = np.zeros((1, FIELD_DIM))
                    e[0, q] = 1.0
                    blocks.append(sps.csr_matrix(np.ones((n, 1)) @ e))
                out.append(sps.hstack(blocks, format="csr"))
            return out
        blocks = weight_rows(self.basis(), self.kernel, X)
        M = self.num_basis
        rows = []
        for q in range(FIELD_DIM):
            A = np.zeros((X.shape[0], self.size))
            if self.kernel == "se":
                A[:, q * M : (q + 1) * M] = blocks[0]
            else:
                A[:, :M] = blocks[q]
            if self.constant_field:
                A[:, n_w + q] = 1.0
            rows.append(A)
        return rows

    def field(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) the posterior mean of the field at points X (n, d)."""
        X = self._points(X)
        out = np.empty((X.shape[0], FIELD_DIM))
        for r in chunks(X.shape[0]):
            for q, A in enumerate(self.design(X[r])):
                out[r, q] = A @ self.mean
        return out

    def std(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) the posterior standard deviation of the field at points X (n, d), from
        the precision's Cholesky factor (a box) or the covariance it gives (tiles: a
        point's rows are sparse, so a^T Sigma a reads a few of its entries)."""
        X = self._points(X)
        out = np.empty((X.shape[0], FIELD_DIM))
        if self.tiles is not None:
            return self._tiled_std(X)
        L = self.cholesky()
        for r in chunks(X.shape[0]):
            for q, A in enumerate(self.design(X[r])):
                V = sla.solve_triangular(L, A.T, lower=True)
                out[r, q] = np.sqrt(np.sum(V * V, axis=0))
        return out

    def _tiled_std(self, X: np.ndarray) -> np.ndarray:
        """:meth:`std` of a tiled map: the points of one grid cell read the same columns
        (its corner tiles' weights and c), so each cell's variances are one dense product
        with that block of the covariance (a sparse-times-dense product with the whole
        covariance took 8 s for 1,000 points of a 2,490-unknown map)."""
        Sigma = self._covariance
        tiles = self.tiled_basis()
        out = np.empty((X.shape[0], FIELD_DIM))
        cells, cell_of = np.unique(tiles.cells(X), axis=0, return_inverse=True)
        for cell in range(cells.shape[0]):
            r = np.flatnonzero(cell_of.ravel() == cell)
            for q, A in enumerate(self.design(X[r])):
                cols = np.unique(A.indices)
                a = A[:, cols].toarray()
                var = np.einsum("ij,ij->i", a @ Sigma[np.ix_(cols, cols)], a)
                out[r, q] = np.sqrt(np.maximum(var, 0.0))
        return out

    def prior_std(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) the GP prior's standard deviation of the field at points X (n, d) in the
        map's basis, the constant field left out: what the map would know without data."""
        X = self._points(X)
        out = np.empty((X.shape[0], FIELD_DIM))
        if self.tiles is not None:
            tiles = self.tiled_basis()
            S = np.tile(tiles.prior_variances(self.sigma_f, self.lengthscale), tiles.num_tiles)
            for r in chunks(X.shape[0]):
                A, n = tiles.design(X[r]), X[r].shape[0]
                var = A.multiply(A) @ S
                out[r] = np.sqrt(var.reshape(FIELD_DIM, n).T)
            return out
        basis = self.basis()
        S = np.ravel(basis.prior_variances(self.kernel, self.sigma_f, self.lengthscale))
        for r in chunks(X.shape[0]):
            blocks = weight_rows(basis, self.kernel, X[r])
            for q in range(FIELD_DIM):
                a = blocks[0 if self.kernel == "se" else q]
                out[r, q] = np.sqrt((a**2 * S).sum(axis=1))
        return out

    def grid(self, points: int = GRID_POINTS, z: float | None = None) -> dict[str, np.ndarray]:
        """The map on a points x points horizontal grid over its box (3-D maps at height z,
        default the box's centre): ``map_x``, ``map_y`` (G, G) [m], ``map_z`` (3-D),
        ``map_field``, ``map_std``, ``map_prior_std`` (G, G, 3) (field units); a tiled
        map's is NaN where the point lacks one of its tiles."""
        c, h = np.asarray(self.center), np.asarray(self.half_width)
        gx, gy = np.meshgrid(
            np.linspace(c[0] - h[0], c[0] + h[0], points),
            np.linspace(c[1] - h[1], c[1] + h[1], points),
        )
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        out: dict[str, np.ndarray] = {"map_x": gx, "map_y": gy}
        if self.dim == 3:
            height = float(c[2] if z is None else z)
            pts = np.column_stack([pts, np.full(pts.shape[0], height)])
            out["map_z"] = np.array(height)
        shape = (*gx.shape, FIELD_DIM)
        inside = self.inside(pts) if self.tiles is not None else np.ones(pts.shape[0], bool)
        std = self.std if self.has_posterior else None  # a mean-only map's: NaN
        for key, of in (("map_field", self.field), ("map_std", std),
                        ("map_prior_std", self.prior_std)):  # fmt: skip
            values = np.full((pts.shape[0], FIELD_DIM), np.nan)
            if of is not None:
                values[inside] = of(pts[inside])
            out[key] = values.reshape(shape)
        return out

    def cholesky(self) -> np.ndarray:
        """Lower Cholesky factor of the precision (raises DataError when it is not
        positive definite), factorised once per map."""
        return self._factor

    @cached_property
    def _factor(self) -> np.ndarray:
        self.require_posterior("map", "give its standard deviation")
        assert self.precision is not None
        try:
            return np.linalg.cholesky(0.5 * (self.precision + self.precision.T))
        except np.linalg.LinAlgError:
            raise DataError("map: its precision matrix is not positive definite") from None

    @cached_property
    def _covariance(self) -> np.ndarray:
        """The inverse of the precision, from its Cholesky factor."""
        inv, info = sla.lapack.dpotri(self.cholesky(), lower=1)
        if info != 0:
            raise DataError(f"map: its precision matrix could not be inverted (LAPACK {info})")
        return np.tril(inv) + np.tril(inv, -1).T

    def inside(self, X: np.ndarray) -> np.ndarray:
        """(n,) whether each point lies in the basis box (outside it the map is only its
        constant: the basis functions vanish on the box's boundary), or for tiles has
        every tile around it."""
        X = self._points(X)
        if self.tiles is not None:
            return self.tiled_basis().inside(X)
        c, h = np.asarray(self.center)[: self.dim], np.asarray(self.half_width)[: self.dim]
        return np.all(np.abs(X - c) <= h, axis=1)

    def _points(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if X.shape[1] != self.dim:
            raise ValueError(f"points of dimension {X.shape[1]} for a {self.dim}-D map")
        return X

    def save(self, path: str | Path) -> Path:
        """Write the map to ``path`` (npz, no pickles) through a temporary name, so that a
        reader never sees half a file."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        layout: dict[str, np.ndarray] = {}
        if self.precision is None:
            layout["mean_only"] = np.array(True)
        elif self.tiles is None:
            layout["precision"] = self.precision
        else:  # symmetric: its upper triangle, row by row, half the file of a dense one
            layout["precision_upper"] = _upper(self.precision)
        if self.tiles is not None:
            g = self.tiles
            layout.update(
                tiles_spacing=np.array(float(g.spacing)),
                tiles_origin=np.asarray(g.origin, dtype=float),
                tiles_index=np.array(g.tiles, dtype=np.int64).reshape(-1, g.dim),
                tiles_basis=np.array(json.dumps(g.basis)),
            )
        with open(tmp, "wb") as f:
            np.savez(
                f,
                format=np.array(FORMAT if self.tiles is None else TILED_FORMAT),
                kernel=np.array(self.kernel),
                center=np.asarray(self.center, dtype=float),
                half_width=np.asarray(self.half_width, dtype=float),
                num_basis=np.array(self.num_basis),
                sigma_f=np.array(self.sigma_f),
                lengthscale=np.array(self.lengthscale),
                sigma_m=np.array(self.sigma_m),
                constant_field=np.array(self.constant_field),
                mean=self.mean,
                frame=np.array(self.frame),
                position_dim=np.array(self.dim),
                **layout,
            )
        os.replace(tmp, path)
        return path


def tiled_map(
    grid: TileGrid,
    hyper: dict[str, float],
    mean: np.ndarray,
    precision: np.ndarray | None,
    constant_field: bool,
    frame: str = "",
) -> SavedMap:
    """The saved map of tiles on ``grid`` (mean and precision of z = [vec(W); c], W (m, T);
    precision None: the mean alone): its box the tile centres' bounding box."""
    idx = np.array(grid.tiles, dtype=float).reshape(-1, grid.dim)
    centres = np.asarray(grid.origin) + grid.spacing * idx
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    return SavedMap(
        kernel="curl_free",
        center=tuple(float(v) for v in 0.5 * (lo + hi)),
        half_width=tuple(float(v) for v in 0.5 * (hi - lo)),
        num_basis=cached_tiles(grid).per_tile,
        sigma_f=float(hyper["sigma_f"]),
        lengthscale=float(hyper["lengthscale"]),
        sigma_m=float(hyper["sigma_m"]),
        constant_field=constant_field,
        mean=mean,
        precision=precision,
        frame=frame,
        position_dim=grid.dim,
        tiles=grid,
    )


#: Most weights for which :func:`tiled_std_given_path` computes a tiled map's standard
#: deviation (a dense covariance: 288 MB at 6,000, the most a run saves,
#: casmag.solver.uncertainty.MAP_MAX_UNKNOWNS).
TILED_STD_MAX_WEIGHTS = 6_000


def tiled_std_given_path(
    grid: TileGrid, hyper: dict[str, float], P: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """(posterior std, prior std), each (G, 3) per field component at points X (G, d), of
    the tiled map on ``grid`` given the magnetometer (noise ``hyper["sigma_m"]``) at the
    positions P (N, d) taken as known: precision A^T A / sigma_m^2 + diag(1 / S), the
    constant field left out (every sample informs it), as the box map's
    (casmag.gp.fieldmap.reduced_rank_std). NaN where a point lacks one of its tiles; None
    above TILED_STD_MAX_WEIGHTS weights."""
    tiles = cached_tiles(grid)
    n_w = tiles.num_weights
    if n_w > TILED_STD_MAX_WEIGHTS:
        return None
    S = np.tile(np.ravel(tiles.prior_variances(hyper["sigma_f"], hyper["lengthscale"])),
                tiles.num_tiles)  # fmt: skip
    A = tiles.design(np.asarray(P, dtype=float))
    precision = (A.T @ A).toarray() / hyper["sigma_m"] ** 2
    precision[np.diag_indices(n_w)] += 1.0 / S
    given = tiled_map(grid, hyper, np.zeros(n_w), precision, False)
    X = given._points(X)
    inside = given.inside(X)
    post, prior = (np.full((X.shape[0], FIELD_DIM), np.nan) for _ in range(2))
    post[inside], prior[inside] = given.std(X[inside]), given.prior_std(X[inside])
    return post, prior


def _marginal_precision(
    nlp: Any, x: dict[str, np.ndarray], params: dict[str, Any], names: list[str],
    fixed: tuple[str, ...],
) -> np.ndarray:  # fmt: skip
    """The Schur complement H_zz - H_za H_aa^-1 H_az of the NLP's Hessian at x for the map
    unknowns ``names`` (z), the variables ``fixed`` left out (:func:`map_from_solution`)."""
    import scipy.sparse.linalg as spla

    H = nlp.hessian(x, params).tocsr()

    def indices(name: str) -> np.ndarray:
        return nlp.x_layout.entries[name].offset + np.arange(nlp.x_layout.entries[name].size)

    z = np.concatenate([indices(n) for n in names])
    held = [indices(n) for n in fixed if n in nlp.x_layout.entries]
    a = np.setdiff1d(np.arange(H.shape[0]), np.concatenate([z, *held]))
    H_zz = H[z][:, z].toarray()
    # The box's border is dense (every sample touches every weight): BLAS, not a sparse
    # product (a 16,000-sample walk's 3,200 x 2,364 border: about 10 s as a scipy sparse
    # product); a tiled map's is sparse (a sample touches the map around it), and its
    # sparse product the faster (casmag.linalg.dense_product).
    H_az = H[a][:, z]
    X = spla.splu(H[a][:, a].tocsc()).solve(H_az.toarray())
    return H_zz - dense_product(H_az.T, X)


def _upper(A: np.ndarray) -> np.ndarray:
    """The upper triangle of a square matrix, row by row (n (n + 1) / 2 values)."""
    return np.concatenate([A[i, i:] for i in range(A.shape[0])])


def _from_upper(path: Path, u: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose upper triangle, row by row, is ``u``."""
    n = (math.isqrt(8 * u.size + 1) - 1) // 2
    if u.ndim != 1 or n * (n + 1) // 2 != u.size:
        raise DataError(f"{path}: precision_upper: {u.size} values are no square's upper triangle")
    A = np.empty((n, n))
    start = 0
    for i in range(n):
        A[i, i:] = u[start : start + n - i]
        A[i:, i] = A[i, i:]
        start += n - i
    return A


def _tuples(value: Any) -> Any:
    """JSON's lists back to the tuples of a grid's basis key."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def write_grid_csv(grid: dict[str, np.ndarray], path: Path) -> None:
    """The arrays of :meth:`SavedMap.grid` as CSV, a row per grid point: x, y (and z) [m],
    mx, my, mz, std_x, std_y, std_z, prior_std_x, prior_std_y, prior_std_z (field units)."""
    cols = [grid["map_x"].ravel(), grid["map_y"].ravel()]
    names = ["x", "y"]
    if "map_z" in grid:
        cols.append(np.full(cols[0].size, float(grid["map_z"])))
        names.append("z")
    for key, stem in (("map_field", "m"), ("map_std", "std_"), ("map_prior_std", "prior_std_")):
        cols.extend(grid[key].reshape(-1, FIELD_DIM).T)
        names.extend(f"{stem}{a}" for a in "xyz")
    np.savetxt(
        path, np.column_stack(cols), fmt="%.9g", delimiter=",", header=",".join(names), comments=""
    )


def load_map(path: str | Path) -> SavedMap:
    """A map written by :meth:`SavedMap.save` (a result folder: its ``map.npz``). Raises
    DataError with one line naming the file and the field when it is not one."""
    path = Path(path)
    if path.is_dir():
        path = path / MAP_FILE
    if not path.is_file():
        raise DataError(f"{path}: no such map file (casmag slam writes {MAP_FILE})")
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise DataError(f"{path}: not a casmag map ({exc})") from None
    if "precision_upper" in data and "precision" not in data:
        data["precision"] = _from_upper(path, np.asarray(data["precision_upper"], dtype=float))
    mean_only = "mean_only" in data and bool(data["mean_only"])
    absent = [k for k in _FIELDS if k not in data and not (mean_only and k == "precision")]
    if absent:
        raise DataError(f"{path}: not a casmag map (no {', '.join(absent)})")
    version = int(data["format"])
    if version not in (FORMAT, TILED_FORMAT):
        raise DataError(f"{path}: format {version}, this casmag reads {FORMAT} and {TILED_FORMAT}")
    tiles = None
    if version == TILED_FORMAT:
        absent = [k for k in _TILE_FIELDS if k not in data]
        if absent:
            raise DataError(f"{path}: a tiled map without {', '.join(absent)}")
        try:
            index = np.asarray(data["tiles_index"], dtype=np.int64)
            tiles = TileGrid(
                float(data["tiles_spacing"]),
                tuple(float(v) for v in data["tiles_origin"]),
                tuple(tuple(int(v) for v in row) for row in index),
                _tuples(json.loads(str(data["tiles_basis"]))),
            )
            tiles_ok = (
                index.ndim == 2
                and index.shape[1] == len(tiles.origin)
                and len(set(tiles.tiles)) == len(tiles.tiles) > 0
                and tiles.spacing > 0
            )
        except (TypeError, ValueError) as exc:
            raise DataError(f"{path}: tiles_*: not a tile grid ({exc})") from None
        if not tiles_ok:
            raise DataError(
                f"{path}: tiles_index must be distinct (tiles, {len(tiles.origin)}) integers "
                "and tiles_spacing positive"
            )

    def number(key: str) -> float:
        v = float(data[key])
        if not np.isfinite(v) or v <= 0:
            raise DataError(f"{path}: {key} must be a positive number, got {v}")
        return v

    try:
        return SavedMap(
            kernel=str(data["kernel"]),
            center=tuple(float(v) for v in data["center"]),
            half_width=tuple(float(v) for v in data["half_width"]),
            num_basis=int(data["num_basis"]),
            sigma_f=number("sigma_f"),
            lengthscale=number("lengthscale"),
            sigma_m=number("sigma_m"),
            constant_field=bool(data["constant_field"]),
            mean=np.asarray(data["mean"], dtype=float),
            precision=None if mean_only else np.asarray(data["precision"], dtype=float),
            frame=str(data["frame"]),
            # absent from the maps of casmag before it: their positions were the box's
            position_dim=int(data["position_dim"]) if "position_dim" in data else None,
            tiles=tiles,
        )
    except (ValueError, TypeError, IndexError) as exc:  # a tiled map's grid is read here
        raise DataError(f"{path}: {exc}") from None


def map_from_solution(
    nlp: Any,
    x: dict[str, np.ndarray],
    params: dict[str, Any],
    kernel: str,
    basis: tuple | TileGrid,
    hyper: dict[str, float],
    frame: str,
    fixed: tuple[str, ...] = (),
    whitened: bool = False,
    position_dim: int | None = None,
    posterior: bool = True,
) -> SavedMap:
    """The saved map of a solved NLP with a map-frame reduced-rank map (variables ``W`` and
    optionally ``c``; ``basis`` the box's key, or a TileGrid for tiles, whose ``W`` is (m,
    T)): mean the solution, precision the Schur complement of the rest of the
    Hessian, H_zz - H_za H_aa^-1 H_az (the inverse of the z block of H^-1: the marginal over
    the path, the bias and every other unknown; module docstring). H_aa (knots and bias) is
    sparse and banded, so this costs one sparse factorisation and a product, not n_z
    solves with the whole Hessian.

    fixed: variables the solve held at their start (NLP.solve's ``fixed``): conditioned on,
    not marginalised. whitened: the NLP's ``W`` holds the whitened weights V of the
    rotated magnetometer models (planar, pose: casmag.model.rotated), W = sqrt(S) V with S
    the prior variances; mean and precision are turned into those of W, the map's own.
    position_dim: the positions the map is read at (default the box's dimension).
    posterior: False saves the mean alone (precision None; no Hessian is evaluated)."""
    names = ["W", *(["c"] if "c" in x else [])]
    mean = np.concatenate([np.ravel(x[n], order="F") for n in names])
    precision = _marginal_precision(nlp, x, params, names, fixed) if posterior else None
    if whitened:
        S = (
            cached_tiles(basis).prior_variances(hyper["sigma_f"], hyper["lengthscale"])
            if isinstance(basis, TileGrid)
            else cached_basis(basis).prior_variances(kernel, hyper["sigma_f"], hyper["lengthscale"])
        )
        rows, cols = np.asarray(x["W"]).shape  # (M, k) or tiles' (m, T): a column at a time
        scale = np.ones(mean.size)
        scale[: rows * cols] = np.tile(np.sqrt(np.ravel(S)), cols)
        mean = scale * mean
        if precision is not None:
            precision = precision / np.outer(scale, scale)
    if precision is not None:
        precision = 0.5 * (precision + precision.T)
    if isinstance(basis, TileGrid):
        return tiled_map(basis, hyper, mean, precision, "c" in x, frame)
    center, half, M = basis
    return SavedMap(
        kernel=kernel,
        center=tuple(float(v) for v in center),
        half_width=tuple(float(v) for v in half),
        num_basis=int(M),
        sigma_f=float(hyper["sigma_f"]),
        lengthscale=float(hyper["lengthscale"]),
        sigma_m=float(hyper["sigma_m"]),
        constant_field="c" in x,
        mean=mean,
        precision=precision,
        frame=frame,
        position_dim=position_dim,
    )
