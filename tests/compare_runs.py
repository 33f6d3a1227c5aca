"""Compare the tidy tables of two run folders of the same study, column by column, to show a
refactor leaves results unchanged. Compute-time columns (``*_ms``) are listed, not compared;
every other column must be equal (``pandas.Series.equals``: same values, NaN where NaN, same
dtype). Run from the repository root::

    python tests/compare_runs.py reports/navigation /tmp/other/navigation

Prints one line per table with a sha256 of its compared data; exits 1 when a table or column
differs.
"""

from __future__ import annotations

import hashlib
import re
import sys
from pathlib import Path

import pandas as pd

COMPUTE_TIME = re.compile(r"_ms$")


def compare(a: Path, b: Path) -> bool:
    """Print the comparison of every ``*.parquet`` of ``a`` with ``b``'s; True when equal."""
    same = True
    names = sorted(p.name for p in a.glob("*.parquet"))
    if names != sorted(p.name for p in b.glob("*.parquet")):
        print(f"tables differ: {names} vs {sorted(p.name for p in b.glob('*.parquet'))}")
        return False
    for name in names:
        da, db = pd.read_parquet(a / name), pd.read_parquet(b / name)
        timing = [c for c in da.columns if COMPUTE_TIME.search(c)]
        if list(da.columns) != list(db.columns) or len(da) != len(db):
            print(f"{name}: columns or rows differ")
            same = False
            continue
        diff = [c for c in da.columns if c not in timing and not da[c].equals(db[c])]
        data = da.drop(columns=timing)
        digest = hashlib.sha256(
            pd.util.hash_pandas_object(data, index=False).values.tobytes()).hexdigest()
        print(f"{name}: {len(da)} rows, {len(da.columns)} columns; compute time not compared: "
              f"{', '.join(timing) or '-'}; differing columns: {', '.join(diff) or 'none'}; "
              f"sha256 of the compared data {digest[:16]}")
        same &= not diff
    return same


if __name__ == "__main__":
    sys.exit(0 if compare(Path(sys.argv[1]), Path(sys.argv[2])) else 1)
