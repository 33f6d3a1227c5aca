"""The sha256 of the C source of every kernel library kind, to show a refactor leaves the
generated C byte-identical.

Covers the sampler libraries (MPPI, SAIS and candidate kernels) of every system of
:data:`~workbench.scenarios.systems.SYSTEMS` on the navigation map, barrier-embedded and
physical, float64 and float32, straight-line and slot-loop (where supported), vector maths on
and off, the default block width and 8 samples per block, the automatic choice; the safe-MPPI
and diagnostics libraries of the same problems; the vector-maths probe and the compiler flags.
Run from the repository root (sources are written to DIR when given)::

    python tests/sampling/kernels/source_hashes.py [DIR] > hashes.txt

and compare two runs' output with ``diff``. The hashes depend on the machine (its vector width
and libmvec), not on the run.
"""

from __future__ import annotations

import hashlib
import sys
import warnings
from pathlib import Path

from workbench.sampling.kernels import diagnostics, safe
from workbench.sampling.kernels import vector_math as vm
from workbench.sampling.kernels.emit import emit_kernel, rng_source
from workbench.sampling.kernels.flags import kernel_flags
from workbench.sampling.kernels.library import kernel_source, library_sources
from workbench.sampling.kernels.slots import SlotLoopUnsupported
from workbench.scenarios.navigation import navigation_setup
from workbench.scenarios.systems import SYSTEMS


def sources():
    """(name, C source or None with the reason it does not exist) of every library kind."""
    for system in SYSTEMS:
        setup = navigation_setup(system=system)
        for label, sp in (("bas", setup.problem), ("phys", setup.physical_problem())):
            for precision in ("float64", "float32"):
                for loop in (False, True):
                    for vmath in (None, False):
                        for lanes in (None, 8):
                            tag = (f"{system}_{label}_{precision}_{'loop' if loop else 'line'}"
                                   f"_vm{vmath}_L{lanes}")
                            try:
                                stem, _, src = library_sources(sp, vmath, precision, lanes,
                                                               loop)
                            except SlotLoopUnsupported as exc:
                                yield tag, None, str(exc)[:60]
                                continue
                            yield f"sampler_{tag}_{stem}", src, ""
                stem, _, src = library_sources(sp, precision=precision)
                yield f"sampler_{system}_{label}_{precision}_auto_{stem}", src, ""
            yield f"safe_{system}_{label}", kernel_source([safe.safe_spec(sp)]), ""
            specs = [diagnostics.sais_diag_spec(sp), diagnostics.gradient_spec(sp),
                     diagnostics.gradient_spec(sp, "augmented")]
            yield f"diag_{system}_{label}", kernel_source(specs), ""
    names = [n for n, _ in vm.VECTOR_FUNCTIONS.values()]
    for precision in ("float64", "float32"):
        spec = vm.probe_spec(precision)
        yield (f"probe_{precision}", rng_source(spec.lanes) + "\n"
               + vm.declarations(names, precision) + emit_kernel(spec), "")
        yield f"flags_{precision}", " ".join(kernel_flags(precision)), ""


def main(argv: list[str]) -> None:
    out = Path(argv[0]) if argv else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    rows = []
    warnings.simplefilter("ignore")
    for name, src, why in sources():
        if src is None:
            rows.append(f"unsupported  {name}: {why}")
            continue
        if out is not None:
            (out / f"{name}.c").write_text(src)
        rows.append(f"{hashlib.sha256(src.encode()).hexdigest()}  {name}")
    print("\n".join(rows))
    print("total", hashlib.sha256("\n".join(rows).encode()).hexdigest())


if __name__ == "__main__":
    main(sys.argv[1:])
