"""The README's bring-your-own-model example runs and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np


def test_readme_unicycle_example_runs():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    block = re.search(r"<!-- example: unicycle -->\s*```python\n(.*?)```", text, re.S)
    assert block, "README example block not found"
    scope: dict = {}
    exec(compile(block.group(1), "README.md", "exec"), scope)
    result, model = scope["result"], scope["model"]
    assert result.converged
    assert scope["min_margin"] > 0
    assert np.linalg.norm(result.X[-1, :2] - [4.0, 0.0]) < 0.1
    # the straight reference crosses the obstacle: the solution went around it
    assert np.max(np.abs(result.X[:, 1])) > 0.3
    assert model.nx == 3 and scope["problem"].nx == 4


def test_readme_sampling_example_continues_the_unicycle():
    """The sampling block, run after the unicycle block in the same scope."""
    text = (Path(__file__).parents[1] / "README.md").read_text()
    blocks = [re.search(rf"<!-- example: {name} -->\s*```python\n(.*?)```", text, re.S)
              for name in ("unicycle", "unicycle-sampling")]
    assert all(blocks), "README example blocks not found"
    scope: dict = {}
    for b in blocks:
        exec(compile(b.group(1), "README.md", "exec"), scope)
    ep = scope["episode"]
    assert not ep.crashed and ep.min_margin > 0
    assert np.linalg.norm(ep.X[-1, :2] - [4.5, 0.5]) < 0.3
