"""Check a loaded sampler kernel against CasADi's own evaluation of the step it was emitted from.

A sampler library is identified by a hash, but a hash only proves the file is the one the
manifest names, not that it computes this problem (a library swapped with another problem's,
manifest updated, loads fine and returns garbage). Before first use every kernel is run on a
small batch (a few samples, including a padded partial block, a few steps) at seeded random
inputs and compared with the CasADi virtual machine stepping the same ``step`` Function sample by
sample and time by time, fed the same noise, then ``final``. Only the kernel's spec is used
(roles of the step inputs), so the check does not depend on how a sampler packs its carries.
"""

from __future__ import annotations

import numpy as np

VERIFY_SAMPLES = 5  # one full block of 4 lanes and a padded one
VERIFY_STEPS = 3
VERIFY_RTOL = 1e-9  # the emitted C equals the VM to rounding (in practice bitwise)


class KernelMismatch(RuntimeError):
    """A compiled kernel disagrees with CasADi's evaluation of its step."""


def _inputs(spec, rng: np.random.Generator, N: int, T: int):
    step = spec.step
    carry = spec.inputs("carry")[0]
    carry0 = rng.uniform(-0.5, 0.5, (N, step.numel_in(carry)))
    time_in = {n: rng.uniform(-1.0, 1.0, (T, step.numel_in(n))) for n in spec.inputs("time")}
    lane_in = {n: rng.uniform(-1.0, 1.0, (T, step.numel_in(n), N)) for n in spec.inputs("lane")}
    consts = {n: rng.uniform(0.5, 1.5, step.numel_in(n)) for n in spec.inputs("const")}
    noise = rng.standard_normal((T, spec.n_noise, N)) if spec.n_noise else None
    return carry0, time_in, lane_in, consts, noise


def reference_rollout(spec, carry0, time_in, lane_in, consts, noise):
    """(lane outputs [(T, m, N)], results (N, nr)) by the CasADi VM, sample by sample."""
    step, final = spec.step, spec.final
    N, T = carry0.shape[0], (noise.shape[0] if noise is not None else
                             next(iter({**time_in, **lane_in}.values())).shape[0])
    lane_out = [np.empty((T, m, N)) for m in spec.lane_out_sizes()]
    results = np.empty((N, spec.n_result))
    for n in range(N):
        c = carry0[n]
        for t in range(T):
            args = []
            for name in step.name_in():
                role = spec.roles[name]
                args.append(c if role == "carry" else noise[t, :, n] if role == "noise"
                            else time_in[name][t] if role == "time"
                            else lane_in[name][t, :, n] if role == "lane" else consts[name])
            out = [np.asarray(o, dtype=float).ravel() for o in step.call(args)]
            c = out[0]
            for j, o in enumerate(out[1:]):
                lane_out[j][t, :, n] = o
        fargs = [c if spec.roles.get(name) == "carry" else consts[name]
                 for name in final.name_in()]
        results[n] = np.concatenate([np.asarray(o, dtype=float).ravel()
                                     for o in final.call(fargs)])
    return lane_out, results


def _agree(ref: np.ndarray, got: np.ndarray) -> bool:
    fin = np.isfinite(ref)
    if not np.array_equal(fin, np.isfinite(got)) or not np.array_equal(np.isnan(ref),
                                                                        np.isnan(got)):
        return False
    scale = max(1.0, float(np.max(np.abs(ref[fin]), initial=0.0)))
    return bool(np.all(np.abs(ref[fin] - got[fin]) <= VERIFY_RTOL * scale)
                and np.array_equal(ref[~fin], got[~fin], equal_nan=True))


def verify_kernel(kernel, seed: int = 20261123) -> None:
    """Raise :class:`KernelMismatch` unless ``kernel`` (a CompiledKernel) equals CasADi's
    evaluation of its spec on a small seeded batch."""
    spec = kernel.spec
    rng = np.random.default_rng(seed)
    carry0, time_in, lane_in, consts, noise = _inputs(spec, rng, VERIFY_SAMPLES, VERIFY_STEPS)
    got = kernel(carry0, consts=consts, time_in=time_in, lane_in=lane_in, noise=noise)
    lane_ref, res_ref = reference_rollout(spec, carry0, time_in, lane_in, consts, noise)
    pairs = [("result", res_ref, got.result)]
    pairs += [(f"lane output {j}", r, g) for j, (r, g) in enumerate(
        zip(lane_ref, got.lane_out, strict=True))]
    for what, ref, g in pairs:
        if np.shape(ref) != np.shape(g) or not _agree(np.asarray(ref), np.asarray(g)):
            raise KernelMismatch(f"compiled kernel {spec.name}: {what} differs from CasADi's "
                                 "evaluation of its step")
