"""Named layouts of the kernels' per-sample carries and results: one object packs and unpacks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.validation import fail


@dataclass(frozen=True)
class Layout:
    """Consecutive named fields of a per-sample vector, e.g. (("x", 5), ("S", 1))."""

    name: str
    fields: tuple[tuple[str, int], ...]

    def __post_init__(self) -> None:
        names = [n for n, _ in self.fields]
        if len(set(names)) != len(names) or any(s < 1 for _, s in self.fields):
            raise ValueError(f"layout {self.name}: field names must be unique, sizes >= 1")

    @property
    def size(self) -> int:
        return sum(s for _, s in self.fields)

    def slices(self) -> dict[str, slice]:
        out, col = {}, 0
        for n, s in self.fields:
            out[n] = slice(col, col + s)
            col += s
        return out

    def pack(self, N: int, **values) -> np.ndarray:
        """(N, size) array; each value is one row (broadcast) or N rows; missing fields are 0."""
        sl = self.slices()
        unknown = set(values) - set(sl)
        if unknown:
            raise fail(f"{self.name} fields", sorted(unknown), f"known fields are {list(sl)}")
        out = np.zeros((N, self.size))
        for n, v in values.items():
            size = sl[n].stop - sl[n].start
            a = np.asarray(v, dtype=float)
            ok = ((), (1,), (N,)) if size == 1 else ((size,), (N, size))
            if a.shape not in ok:
                raise fail(n, a.shape, f"expected a shape in {list(ok)}")
            if not np.all(np.isfinite(a)):
                raise fail(n, a, "all entries must be finite")
            if size == 1:
                out[:, sl[n].start] = a
            else:
                out[:, sl[n]] = a
        return out

    def unpack(self, arr: np.ndarray) -> dict[str, np.ndarray]:
        """Views per field: (N,) for size-1 fields, else (N, size)."""
        if arr.ndim != 2 or arr.shape[1] != self.size:
            raise fail(f"{self.name} array", arr.shape, f"expected (N, {self.size})")
        return {n: arr[:, s] if s.stop - s.start > 1 else arr[:, s.start]
                for n, s in self.slices().items()}
