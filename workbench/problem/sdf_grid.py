"""A signed-distance grid as a run-time obstacle (assumptions §3.4).

The grid holds signed distances (metres; > 0 free, < 0 inside an obstacle) at the nodes
``origin + (i, j) * resolution``, i < nx along x, j < ny along y. Its margin at a position is
the bilinear interpolation of the four surrounding nodes: exact at the nodes, continuous, with
exact first and second derivatives inside each cell (iLQG's: the gradient, the cross term
d2h/dx dy; d2h/dx2 = d2h/dy2 = 0). Beyond the grid a position takes the value of the nearest
point of the grid (the map says nothing there).

In the scene input a grid is ``(ox, oy, resolution, values)`` with the values x-fastest
(``values.T.ravel()`` of an (nx, ny) array); its shape is fixed when the model is built, so a
new map of the same shape (or a moved or rescaled one) builds nothing.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from workbench.validation import as_array, fail, real

HEADER = 3  # ox, oy, resolution
MAX_GRID_NODES = 4_000_000


@dataclass(frozen=True, eq=False)
class SignedDistanceGrid:
    """Signed distances ``values`` (nx, ny) at nodes ``origin + (i, j) * resolution``."""

    values: np.ndarray
    origin: tuple[float, float] = (0.0, 0.0)
    resolution: float = 1.0

    def __post_init__(self) -> None:
        v = as_array("SignedDistanceGrid.values", self.values, (None, None))
        if v.shape[0] < 2 or v.shape[1] < 2:
            raise fail("SignedDistanceGrid.values", f"an array of shape {v.shape}",
                       "needs at least 2 x 2 nodes")
        if v.size > MAX_GRID_NODES:
            raise fail("SignedDistanceGrid.values", f"an array of shape {v.shape}",
                       f"at most {MAX_GRID_NODES} nodes")
        o = as_array("SignedDistanceGrid.origin", self.origin, (2,))
        object.__setattr__(self, "values", np.array(v, dtype=float))
        self.values.flags.writeable = False
        object.__setattr__(self, "origin", (float(o[0]), float(o[1])))
        object.__setattr__(self, "resolution", real("SignedDistanceGrid.resolution",
                                                    self.resolution, 0.0, strict=True))

    def __repr__(self) -> str:
        return (f"SignedDistanceGrid(shape={self.shape}, origin={self.origin}, "
                f"resolution={self.resolution:g})")

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.values.shape[0]), int(self.values.shape[1]))

    def row(self) -> np.ndarray:
        """The grid's block of a scene vector: origin, resolution, values x-fastest."""
        return np.concatenate([[*self.origin, self.resolution], self.values.T.ravel()])

    @classmethod
    def from_row(cls, row, shape: tuple[int, int]) -> SignedDistanceGrid:
        r = np.asarray(row, dtype=float)
        return cls(r[HEADER:].reshape(shape[1], shape[0]).T, (r[0], r[1]), r[2])

    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) of the nodes."""
        (nx, ny), (ox, oy), h = self.shape, self.origin, self.resolution
        return ox, ox + (nx - 1) * h, oy, oy + (ny - 1) * h


def inert_row(shape: tuple[int, int]) -> np.ndarray:
    """An unused grid block: distance 1e8 everywhere (and beyond, by extrapolation)."""
    return np.concatenate([[0.0, 0.0, 1.0], np.full(shape[0] * shape[1], 1e8)])


def check_row(field: str, row: np.ndarray) -> None:
    """Refuse a grid block whose resolution is not > 0 (values are checked finite before)."""
    if not row[2] > 0:
        raise fail(f"{field} (grid resolution)", row[2], "must be > 0")


@functools.lru_cache(maxsize=16)
def row_interpolant(n: int) -> ca.Function:
    """CasADi's linear interpolant on 0..n-1 with the n values as an input: the grid's values
    read along x (node i + nx j at coordinate i + nx j)."""
    return ca.interpolant(f"wb_row_{n}", "linear", [np.arange(n, dtype=float)], 1, {})


def _clamp(x, hi: float):
    """x clamped to [0, hi]; NaN stays NaN (comparisons with NaN are false)."""
    return ca.if_else(x < 0, 0, ca.if_else(x > hi, hi, x))


def grid_sx(p, block, shape: tuple[int, int], inflation: float = 0.0):
    """The grid's margin at position ``p`` (2 SX entries) for a scene block (SX).

    Unit coordinates u, v clamped to the grid, cell (i, j) = (min(floor u, nx - 2), min(floor v,
    ny - 2)), weights a = u - i, b = v - j; the cell's bottom and top edges interpolated along x
    by two calls of the row interpolant over the values (nodes k + a and k + nx + a, k = i + nx
    j), then h = (1 - b) e0 + b e1. Its value is the bilinear interpolation and its derivatives
    are exact inside a cell: gradient, the cross term d2h/du dv = (e1 - e0)'; d2h/du2 = d2h/dv2
    = 0. Beyond the grid the nearest boundary point's value (its gradient across the boundary
    0). A NaN position gives a NaN margin."""
    nx, ny = shape
    u = _clamp((p[0] - block[0]) / block[2], nx - 1)
    v = _clamp((p[1] - block[1]) / block[2], ny - 1)
    i = ca.fmin(ca.floor(u), nx - 2)
    j = ca.fmin(ca.floor(v), ny - 2)
    a, b = u - i, v - j
    k = i + nx * j
    row = row_interpolant(nx * ny)
    values = block[HEADER:HEADER + nx * ny]
    e0 = row(k + a, values)
    e1 = row(k + nx + a, values)
    h = (1 - b) * e0 + b * e1
    return h - inflation if inflation else h


def grid_numpy(P: np.ndarray, row: np.ndarray, shape: tuple[int, int],
               inflation: float = 0.0) -> np.ndarray:
    """The grid's margins (N,) at positions P (N, 2): bilinear in the cell holding each point,
    the nearest boundary point's value beyond the grid, NaN for a NaN position; written
    without CasADi."""
    nx, ny = shape
    V = row[HEADER:].reshape(ny, nx)  # V[j, i]
    u = np.clip((P[:, 0] - row[0]) / row[2], 0, nx - 1)
    v = np.clip((P[:, 1] - row[1]) / row[2], 0, ny - 1)
    bad = np.isnan(u) | np.isnan(v)
    u, v = np.where(bad, 0.0, u), np.where(bad, 0.0, v)
    i = np.minimum(np.floor(u), nx - 2).astype(int)
    j = np.minimum(np.floor(v), ny - 2).astype(int)
    a, b = u - i, v - j
    e0 = (1 - a) * V[j, i] + a * V[j, i + 1]
    e1 = (1 - a) * V[j + 1, i] + a * V[j + 1, i + 1]
    h = (1 - b) * e0 + b * e1
    return np.where(bad, np.nan, h) - inflation
