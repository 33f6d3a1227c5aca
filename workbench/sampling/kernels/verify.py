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

VERIFY_SAMPLES = 5  # at least; float64 checks max(this, lanes + 1): a full block and a padded one
VERIFY_STEPS = 3
VERIFY_RTOL = 1e-9  # the emitted C equals the VM to rounding (in practice bitwise)
# float32: ~1e-6 measured on well-conditioned points (rounding of ~50 operations per step,
# accumulated over the steps); 1e-4 leaves a factor ~100 and still fails any other function
VERIFY_RTOL_F32 = 1e-4
CONDITION_LIMIT = 1e-5  # relative output change from rounding the inputs to float (~170 ulp)
_REDRAWS = 50


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


def _spread(rng: np.random.Generator, shape, positive: bool = False) -> np.ndarray:
    """Magnitudes log-uniform in [0.1, 10], random signs unless ``positive``."""
    v = 10.0 ** rng.uniform(-1.0, 1.0, shape)
    return v if positive else v * rng.choice([-1.0, 1.0], shape)


def _inputs_f32(spec, rng: np.random.Generator, N: int, T: int):
    step = spec.step
    carry = spec.inputs("carry")[0]
    carry0 = _spread(rng, (N, step.numel_in(carry)))
    time_in = {n: _spread(rng, (T, step.numel_in(n))) for n in spec.inputs("time")}
    lane_in = {n: _spread(rng, (T, step.numel_in(n), N)) for n in spec.inputs("lane")}
    consts = {n: _spread(rng, step.numel_in(n), True) for n in spec.inputs("const")}
    noise = rng.standard_normal((T, spec.n_noise, N)) if spec.n_noise else None
    return carry0, time_in, lane_in, consts, noise


def _round32(a):
    if a is None:
        return None
    if isinstance(a, dict):
        return {k: _round32(v) for k, v in a.items()}
    with np.errstate(over="ignore"):
        return np.asarray(a, float).astype(np.float32).astype(float)


def _per_sample_change(ref, alt) -> np.ndarray:
    """Largest relative change per sample between two (lane outputs, results) evaluations."""
    (lr, rr), (la, ra) = ref, alt
    worst = np.max(_rel(rr, ra), axis=1)
    for r, a in zip(lr, la, strict=True):
        worst = np.maximum(worst, np.max(_rel(r, a), axis=(0, 1)))
    return worst


def _rel(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    with np.errstate(invalid="ignore"):
        d = np.abs(a - b) / np.maximum(np.maximum(np.abs(a), np.abs(b)), 1.0)
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    return np.where(same, 0.0, np.where(np.isfinite(d), d, np.inf))


def conditioned_inputs(spec, rng: np.random.Generator, N: int, T: int):
    """Float32 verification inputs (see module docstring) and their double reference."""
    carry0, time_in, lane_in, consts, noise = _inputs_f32(spec, rng, N, T)
    for _ in range(_REDRAWS):
        ref = reference_rollout(spec, carry0, time_in, lane_in, consts, noise)
        alt = reference_rollout(spec, _round32(carry0), _round32(time_in), _round32(lane_in),
                                _round32(consts), _round32(noise))
        bad = np.flatnonzero(_per_sample_change(ref, alt) > CONDITION_LIMIT)
        if bad.size == 0:
            return (carry0, time_in, lane_in, consts, noise), ref
        c2, _, l2, _, z2 = _inputs_f32(spec, rng, N, T)  # new per-sample inputs
        carry0[bad] = c2[bad]
        for n in lane_in:
            lane_in[n][..., bad] = l2[n][..., bad]
        if noise is not None:
            noise[..., bad] = z2[..., bad]
    raise KernelMismatch(f"compiled kernel {spec.name}: no well-conditioned verification "
                         f"points for float32 after {_REDRAWS} draws (the step is too "
                         "sensitive to float rounding; use precision='float64')")


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


def _agree_f32(ref: np.ndarray, got: np.ndarray) -> bool:
    """Per element: |a - b| <= VERIFY_RTOL_F32 max(|a|, |b|, 1), inf and NaN where they are."""
    return bool(np.all(_rel(ref, got) <= VERIFY_RTOL_F32))


def verify_kernel(kernel, seed: int = 20261123) -> None:
    """Raise :class:`KernelMismatch` unless ``kernel`` (a CompiledKernel) equals CasADi's
    evaluation of its spec on a small seeded batch (float32 kernels: to float32 tolerance on
    well-conditioned points of the operating range, :data:`VERIFY_RTOL_F32`)."""
    spec = kernel.spec
    rng = np.random.default_rng(seed)
    if spec.precision == "float32":
        # a full block of lanes and a padded one
        (carry0, time_in, lane_in, consts, noise), (lane_ref, res_ref) = conditioned_inputs(
            spec, rng, spec.lanes + 1, VERIFY_STEPS)
        agree = _agree_f32
    else:
        carry0, time_in, lane_in, consts, noise = _inputs(
            spec, rng, max(VERIFY_SAMPLES, spec.lanes + 1), VERIFY_STEPS)
        lane_ref, res_ref = reference_rollout(spec, carry0, time_in, lane_in, consts, noise)
        agree = _agree
    got = kernel(carry0, consts=consts, time_in=time_in, lane_in=lane_in, noise=noise)
    pairs = [("result", res_ref, got.result)]
    pairs += [(f"lane output {j}", r, g) for j, (r, g) in enumerate(
        zip(lane_ref, got.lane_out, strict=True))]
    for what, ref, g in pairs:
        if np.shape(ref) != np.shape(g) or not agree(np.asarray(ref), np.asarray(g)):
            raise KernelMismatch(f"compiled kernel {spec.name}: {what} differs from CasADi's "
                                 f"evaluation of its step{_range_hint(spec, ref)}")


def _range_hint(spec, ref) -> str:
    """Why a float32 kernel differs when CasADi's values exceed float32's range."""
    a = np.abs(np.asarray(ref, dtype=float))
    big = float(np.max(a[np.isfinite(a)], initial=0.0))
    if spec.precision != "float32" or big <= float(np.finfo(np.float32).max):
        return ""
    return (f" (CasADi's values reach {big:.3g} at the verification points, beyond float32's "
            "range 3.4e38: the model's or the costs' constants are too large for precision "
            "'float32'; use 'float64')")
