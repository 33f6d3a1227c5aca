"""A signed-distance grid as a run-time obstacle (assumptions §3.4).

The grid holds signed distances (metres; > 0 free, < 0 inside an obstacle) at the nodes
``origin + (i, j) * resolution``, i < nx along x, j < ny along y. Its margin at a position is
the bilinear interpolation of the four surrounding nodes: exact at the nodes, continuous,
differentiable inside each cell (iLQG uses the cell's gradient; the second derivative in x or
in y alone is 0). Outside the grid the boundary cells' bilinear form continues (linear
extrapolation), as CasADi's linear interpolant does.

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
def unit_interpolant(nx: int, ny: int) -> ca.Function:
    """CasADi's linear interpolant on the unit grid 0..nx-1 x 0..ny-1 with the values as an
    input (x-fastest); shared by every grid of that shape."""
    return ca.interpolant(f"wb_grid_{nx}x{ny}", "linear",
                          [np.arange(nx, dtype=float), np.arange(ny, dtype=float)], 1, {})


def grid_sx(p, block, shape: tuple[int, int], inflation: float = 0.0):
    """The grid's margin at position ``p`` (2 SX entries) for a scene block (SX)."""
    nx, ny = shape
    u = (p[0] - block[0]) / block[2]
    v = (p[1] - block[1]) / block[2]
    h = unit_interpolant(nx, ny)(ca.vertcat(u, v), block[HEADER:HEADER + nx * ny])
    return h - inflation if inflation else h


def grid_numpy(P: np.ndarray, row: np.ndarray, shape: tuple[int, int],
               inflation: float = 0.0) -> np.ndarray:
    """The grid's margins (N,) at positions P (N, 2): bilinear in the cell holding each point
    (the boundary cells' form beyond the grid), written without CasADi."""
    nx, ny = shape
    V = row[HEADER:].reshape(ny, nx)  # V[j, i]
    u = (P[:, 0] - row[0]) / row[2]
    v = (P[:, 1] - row[1]) / row[2]
    i = np.clip(np.floor(u), 0, nx - 2).astype(int)
    j = np.clip(np.floor(v), 0, ny - 2).astype(int)
    a, b = u - i, v - j
    h = ((1 - a) * (1 - b) * V[j, i] + a * (1 - b) * V[j, i + 1]
         + (1 - a) * b * V[j + 1, i] + a * b * V[j + 1, i + 1])
    return h - inflation
