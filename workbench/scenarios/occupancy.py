"""Occupancy maps from mapping stacks, as signed-distance grids (assumptions §3.4).

:func:`load_map` reads a map the way ROS map_server saves it: a YAML file (``image``,
``resolution``, ``origin: [x, y, yaw]``, ``negate``, ``occupied_thresh``, ``free_thresh`` and
optionally ``mode``: trinary (default), scale or raw) next to a PGM image (binary P5 or ascii
P2, 8- or 16-bit). :meth:`OccupancyMap.from_array` takes a NumPy array instead (bool, or
occupancy probabilities with a threshold). :meth:`OccupancyMap.signed_distance` turns either
into a :class:`~workbench.problem.sdf_grid.SignedDistanceGrid`, inflated by a robot radius.

Cells and nodes: cell (i, j) (i along x, j along y) is the square
``origin + [i, i + 1] x [j, j + 1] * resolution``; ``origin`` is the lower-left corner of
cell (0, 0), as in map_server. The image's row 0 is the top of the map: pixel (row r,
column c) of an image of height H is cell (c, H - 1 - r). The grid's node (i, j) sits at the
centre of cell (i, j), ``origin + (i + 1/2, j + 1/2) * resolution``.

Pixel values, as map_server reads them: ``p = (maxval - v) / maxval`` (``v / maxval`` with
``negate: 1``; maxval 255 or 65535); p > occupied_thresh is occupied, p < free_thresh free,
anything between unknown. ``mode: scale`` classifies cells the same way (map_server gives the
cells between the thresholds a graded value; here they are unknown cells). ``mode: raw``:
the pixel value is the occupancy in percent, p = v / 100, values above 100 are unknown.
Unknown cells count as occupied by default (``unknown="free"`` to count them as free).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

from workbench.problem.sdf_grid import MAX_GRID_NODES, SignedDistanceGrid
from workbench.validation import as_array, fail, one_of, real

UNKNOWN = ("occupied", "free")
MODES = ("trinary", "scale", "raw")
YAML_FIELDS = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh",
               "mode")
CORNER_EXCESS = (np.sqrt(2.0) - 1.0) / 2.0  # at most this many cells optimistic, see below


@dataclass(frozen=True, eq=False)
class OccupancyMap:
    """Occupied cells ``occupied`` (nx, ny) (bool, [i, j] = cell i along x, j along y) of side
    ``resolution`` (m), cell (0, 0)'s lower-left corner at ``origin`` (see the module)."""

    occupied: np.ndarray
    resolution: float
    origin: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        occ = np.asarray(self.occupied)
        if occ.dtype != bool or occ.ndim != 2:
            raise fail("OccupancyMap.occupied", f"an array of shape {occ.shape} and type "
                       f"{occ.dtype}", "a 2-D bool array (cell i along x, j along y)")
        if occ.shape[0] < 2 or occ.shape[1] < 2 or occ.size > MAX_GRID_NODES:
            raise fail("OccupancyMap.occupied", f"an array of shape {occ.shape}",
                       f"needs at least 2 x 2 and at most {MAX_GRID_NODES} cells")
        occ = occ.copy()
        occ.flags.writeable = False
        object.__setattr__(self, "occupied", occ)
        object.__setattr__(self, "resolution", real("OccupancyMap.resolution",
                                                    self.resolution, 0.0, strict=True))
        o = as_array("OccupancyMap.origin", self.origin, (2,))
        object.__setattr__(self, "origin", (float(o[0]), float(o[1])))

    @classmethod
    def from_array(cls, occupancy, resolution: float, origin=(0.0, 0.0),
                   threshold: float = 0.5) -> OccupancyMap:
        """A map from an array indexed [i, j] (cell i along x, j along y; for an image with
        row 0 at the top pass ``np.flipud(image).T``): bool (True occupied) or occupancy
        probabilities in [0, 1], occupied where p > ``threshold``."""
        a = np.asarray(occupancy)
        if a.dtype != bool:
            p = as_array("occupancy", a, (None, None))
            if np.any((p < 0) | (p > 1)):
                raise fail("occupancy", f"values in [{p.min():g}, {p.max():g}]",
                           "a bool array or probabilities in [0, 1]")
            t = real("threshold", threshold, 0.0, maximum=1.0)
            a = p > t
        return cls(a, resolution, origin)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.occupied.shape[0]), int(self.occupied.shape[1]))

    def cell_centre(self, i, j) -> np.ndarray:
        """Centre(s) of cell (i, j): ``origin + (i + 1/2, j + 1/2) * resolution``."""
        h = self.resolution
        return np.stack([self.origin[0] + (np.asarray(i) + 0.5) * h,
                         self.origin[1] + (np.asarray(j) + 0.5) * h], axis=-1)

    def signed_distance(self, inflation: float = 0.0) -> SignedDistanceGrid:
        """The signed-distance grid of this map, nodes at the cell centres, minus
        ``inflation`` (the robot's radius, m).

        Before inflation the value at a free cell's centre is its Euclidean distance to the
        nearest occupied cell's centre minus half a cell, at an occupied cell's centre minus
        (its distance to the nearest free cell's centre minus half a cell)
        (:func:`scipy.ndimage.distance_transform_edt`): between a free and an occupied
        neighbour the grid crosses 0 on their shared edge. Where the nearest occupied cell
        lies along a row or column of the free node, this is the exact distance to the
        occupied squares; towards a corner it exceeds it by at most (sqrt 2 - 1) / 2 cells
        (:data:`CORNER_EXCESS`): add ``CORNER_EXCESS * resolution`` to the inflation for a
        bound that never overstates the clearance at the nodes. Beyond the outermost
        nodes (the map's outer half cells and its outside) a position takes the value of the
        nearest point of the grid (:mod:`workbench.problem.sdf_grid`). A map without an
        occupied or without a free cell is refused."""
        r = real("inflation", inflation, 0.0)
        occ, h = self.occupied, self.resolution
        if not occ.any() or occ.all():
            raise fail("OccupancyMap.occupied", f"{int(occ.sum())} of {occ.size} cells "
                       "occupied", "a signed-distance grid needs at least one occupied and "
                       "one free cell")
        outside = ndimage.distance_transform_edt(~occ)  # free cells: distance to occupied
        inside = ndimage.distance_transform_edt(occ)  # occupied cells: distance to free
        d = h * np.where(occ, 0.5 - inside, outside - 0.5) - r
        origin = (self.origin[0] + h / 2, self.origin[1] + h / 2)
        return SignedDistanceGrid(d, origin, h)


def _number(path: Path, name: str, value, lo: float | None = None,
            hi: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise fail(f"{path}: {name}", value, "must be a number")
    return real(f"{path}: {name}", value, lo, maximum=hi)


def load_map(path, unknown: str = "occupied") -> OccupancyMap:
    """The map of a map_server YAML file and its image (see the module): ``image`` relative to
    the YAML file's folder unless absolute; ``origin`` [x, y, yaw] with yaw 0 (a rotated map is
    refused); ``unknown``: "occupied" (default) or "free", what unknown cells count as.
    Missing or unknown fields, bad values and unreadable images are refused naming the file,
    the field and the value."""
    one_of("unknown", unknown, UNKNOWN)
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise fail("map file", str(path), f"cannot be read ({exc.strerror})") from exc
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise fail("map file", str(path), f"is not valid YAML ({exc})") from exc
    if not isinstance(meta, dict):
        raise fail("map file", str(path), "must hold a YAML mapping of the map_server fields "
                   f"{YAML_FIELDS}")
    extra = sorted(str(k) for k in meta if k not in YAML_FIELDS)
    if extra:
        raise fail(f"{path}: {extra[0]}", meta[extra[0]], f"unknown field; the fields are "
                   f"{YAML_FIELDS}")
    missing = [k for k in YAML_FIELDS if k != "mode" and k not in meta]
    if missing:
        raise fail(f"{path}: {missing[0]}", None, "missing; a map_server map needs "
                   f"{[k for k in YAML_FIELDS if k != 'mode']}")
    res = _number(path, "resolution", meta["resolution"])
    if not res > 0:
        raise fail(f"{path}: resolution", meta["resolution"], "must be > 0 (m per cell)")
    origin = meta["origin"]
    if (not isinstance(origin, list) or len(origin) != 3
            or any(isinstance(v, bool) or not isinstance(v, int | float) for v in origin)):
        raise fail(f"{path}: origin", origin, "must be [x, y, yaw] (three numbers)")
    for v in origin:
        _number(path, "origin", v)
    if origin[2] != 0:
        raise fail(f"{path}: origin", origin, "a yaw other than 0 (a rotated map) is not "
                   "supported; rotate the image instead")
    negate = meta["negate"]
    if negate not in (0, 1) or isinstance(negate, float):
        raise fail(f"{path}: negate", negate, "must be 0 or 1")
    occ_t = _number(path, "occupied_thresh", meta["occupied_thresh"], 0.0, 1.0)
    free_t = _number(path, "free_thresh", meta["free_thresh"], 0.0, 1.0)
    if not free_t <= occ_t:
        raise fail(f"{path}: free_thresh", free_t, f"must be <= occupied_thresh = {occ_t:g}")
    mode = meta.get("mode", "trinary")
    if mode not in MODES:
        raise fail(f"{path}: mode", mode, f"must be one of {MODES}")
    image = meta["image"]
    if not isinstance(image, str) or not image:
        raise fail(f"{path}: image", image, "must be the image file's name")
    img_path = Path(image) if Path(image).is_absolute() else path.parent / image
    try:
        pixels, maxval = read_pgm(img_path)
    except ValueError as exc:
        raise fail(f"{path}: image", image, str(exc)) from exc
    v = pixels.astype(float)
    if mode == "raw":
        p = v / 100.0
        unknown_px = v > 100
    else:
        p = v / maxval if negate else (maxval - v) / maxval
        unknown_px = np.zeros(v.shape, dtype=bool)
    occupied = (p > occ_t) & ~unknown_px
    free = (p < free_t) & ~unknown_px
    unknown_px |= ~occupied & ~free
    cells = occupied | (unknown_px if unknown == "occupied" else np.zeros_like(occupied))
    try:
        return OccupancyMap(np.flipud(cells).T, res, (float(origin[0]), float(origin[1])))
    except ValueError as exc:
        raise fail("map file", str(path), str(exc)) from exc


def read_pgm(path) -> tuple[np.ndarray, int]:
    """The pixels (height, width) (row 0 at the top) and maxval of a PGM image: binary (P5,
    big-endian for maxval > 255) or ascii (P2), header comments allowed."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise fail("image", str(path), f"cannot be read ({exc.strerror})") from exc
    magic = data[:2]
    if magic not in (b"P5", b"P2"):
        raise fail("image", str(path), f"starts with {magic!r}: not a PGM image (P5 or P2)")
    fields: list[int] = []
    pos = 2
    while len(fields) < 3:
        while pos < len(data) and (data[pos:pos + 1].isspace() or data[pos:pos + 1] == b"#"):
            if data[pos:pos + 1] == b"#":
                end = data.find(b"\n", pos)
                pos = len(data) if end < 0 else end
            pos += 1
        start = pos
        while pos < len(data) and data[pos:pos + 1].isdigit():
            pos += 1
        if start == pos:
            raise fail("image", str(path), "has a truncated or malformed PGM header (width, "
                       "height, maxval)")
        fields.append(int(data[start:pos]))
    width, height, maxval = fields
    if width < 1 or height < 1 or not 1 <= maxval <= 65535:
        raise fail("image", str(path), f"has width {width}, height {height}, maxval {maxval}; "
                   "PGM needs width, height >= 1 and maxval in [1, 65535]")
    n = width * height
    if magic == b"P5":
        body = data[pos + 1:]
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype("u1")
        if len(body) < n * dtype.itemsize:
            raise fail("image", str(path), f"holds {len(body)} bytes of pixels, "
                       f"{n * dtype.itemsize} expected for {width} x {height}")
        px = np.frombuffer(body, dtype=dtype, count=n)
    else:
        tokens = data[pos:].split()
        if len(tokens) < n or not all(t.isdigit() for t in tokens[:n]):
            raise fail("image", str(path), f"holds {len(tokens)} ascii values, {n} whole "
                       f"numbers expected for {width} x {height}")
        px = np.array([int(t) for t in tokens[:n]])
    if px.max() > maxval:
        raise fail("image", str(path), f"has a pixel value {int(px.max())} above maxval "
                   f"{maxval}")
    return px.reshape(height, width).astype(np.int64), maxval
