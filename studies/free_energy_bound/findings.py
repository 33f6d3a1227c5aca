"""Every interpretive sentence of the report, as a claim whose condition is computed from the
summary's numbers; the report prints only the claims that hold."""

from __future__ import annotations

from studies.free_energy_bound.failures import CAUSES
from studies.free_energy_bound.paper import LOOSE_FACTOR, USEFUL_LOCALISATION
from studies.free_energy_bound.summary import BoundSummary
from workbench.study import Claim, Rate

FORMS = {"T3": "the lemma as printed", "T3b": "the lemma with the proof's δ",
         "T3c": "a variant with α_t and F̂_nom(t+1), not implied by the lemma",
         "T3d": "the implied absolute form"}


def _v(v: float) -> str:
    return f"{v:g}"


def holds_claims(s: BoundSummary) -> list[Claim]:
    out = []
    for test in s.config["tests"]:
        for c in ("local", "global"):
            rows = [r for v in s.variances if (r := s.row(test, c, v.variance)) is not None]
            if not rows:
                continue
            n, k = sum(r.n_steps for r in rows), sum(r.n_holding for r in rows)
            out.append(Claim(f"{test} ({c} constants) held at every one of the {n} steps where "
                             "it was evaluated, at every variance.", k == n, f"{k}/{n}"))
            where = ", ".join(f"variance {_v(r.variance)}: {r.n_steps - r.n_holding} of "
                              f"{r.n_steps}" for r in rows if r.n_holding < r.n_steps)
            out.append(Claim(f"{test} ({c} constants) failed at {n - k} of {n} steps ({where}).",
                             k < n, f"{k}/{n}"))
    return out


def safe_step_claims(s: BoundSummary) -> list[Claim]:
    n_safe = {v.variance: v.n_all_real_safe for v in s.variances}
    none = [_v(v) for v, n in n_safe.items() if n == 0]
    fails = [f for f in s.t1_failures_safe if f.constants == "local"]
    out = [Claim(f"At variance {', '.join(none)} no step had all real samples inside the safe "
                 "set, so the stratum where T1 must hold by the tube argument is empty there.",
                 bool(none)),
           Claim(f"T1 held at every one of the {sum(n_safe.values())} steps where all real samples "
                 "stayed safe (local and global constants).",
                 sum(n_safe.values()) > 0 and not s.t1_failures_safe)]
    for cause, text in CAUSES.items():
        hit = [f for f in fails if f.cause == cause]
        steps = "; ".join(f"variance {_v(f.variance)}, episode {f.episode}, step {f.step} "
                          f"({f.test}, slack {f.slack:.3g}, R {f.R:.3g}, L_q {f.L_q:.3g}, "
                          f"secant {f.secant_q:.3g})" for f in hit[:10])
        out.append(Claim(f"{len(hit)} T1 failure(s) with local constants at steps where all "
                         f"real samples stayed safe: {steps}. Cause: {text}.", bool(hit)))
    return out


def looseness_claims(s: BoundSummary, no_barrier_L_q: float) -> list[Claim]:
    out = []
    for v in s.variances:
        if v.L_q_local.n == 0:
            continue
        ratio = v.delta_local.median / v.F_real_abs_median
        out.append(Claim(
            f"Variance {_v(v.variance)}: the local Lipschitz constants are huge — over the "
            f"{v.L_q_local.n} steps with R > 0, L_q has median {v.L_q_local.median:.3g} (range "
            f"{v.L_q_local.min:.3g} to {v.L_q_local.max:.3g}), L_phi median "
            f"{v.L_phi_local.median:.3g}; δ = (L_φ + n_q L_q) R has median "
            f"{v.delta_local.median:.3g}, {ratio:.2g} times the median |F̂_real| "
            f"({v.F_real_abs_median:.3g}): the bound holds but is loose.",
            ratio > LOOSE_FACTOR, f"δ/|F| = {ratio:.3g} > {LOOSE_FACTOR:g}"))
        out.append(Claim(
            f"Variance {_v(v.variance)}: over the {v.L_q_local.n} steps with R > 0 the local "
            f"L_q has median {v.L_q_local.median:.3g} (range {v.L_q_local.min:.3g} to "
            f"{v.L_q_local.max:.3g}) and δ median {v.delta_local.median:.3g}, {ratio:.2g} times "
            f"the median |F̂_real| ({v.F_real_abs_median:.3g}): on most of these steps the "
            "tube stays away from the obstacles and the bound is of the order of the free "
            "energy itself.", ratio <= LOOSE_FACTOR and v.L_q_local.median <= no_barrier_L_q,
            f"δ/|F| = {ratio:.3g}, median L_q <= {no_barrier_L_q:.3g}"))
        out.append(Claim(
            f"Variance {_v(v.variance)}: the median local L_q ({v.L_q_local.median:.3g}) is "
            f"{v.L_q_local.median / no_barrier_L_q:.2g} times the largest gradient of the same "
            f"cost anywhere on the map when β is a coordinate and not B(h(p)) "
            f"({no_barrier_L_q:.3g}): it is set by the barrier term "
            "2 q_β (β − β_g) Σ B'(h_i) ∇h_i near obstacles.",
            v.L_q_local.median > no_barrier_L_q))
        r = v.L_q_ratio_median
        out.append(Claim(f"Variance {_v(v.variance)}: the global L_q ({v.L_q_global:.3g}) is "
                         f"only {r:.3g} times the local one (median over steps with R > 0): "
                         "localisation buys little here.", r < USEFUL_LOCALISATION))
        out.append(Claim(f"Variance {_v(v.variance)}: localisation shrinks L_q by a factor "
                         f"{r:.3g} (median global/local over steps with R > 0).",
                         r >= USEFUL_LOCALISATION))
    return out


def transition_claims(s: BoundSummary) -> list[Claim]:
    out = []
    for t in ("T3", "T3b", "T3c", "T3d"):
        f = [x for x in s.transition_failures if x.test == t and x.constants == "local"]
        n, p = sum(x.n_failed for x in f), sum(x.n_premise_fails for x in f)
        fb, first = sum(x.n_fallback for x in f), sum(x.n_first_step for x in f)
        at = "t+1" if t in ("T3c", "T3d") else "t"
        out.append(Claim(f"Every {t} failure with local constants ({n}) is at a transition whose "
                         f"nominal state at {at} is not admissible (F̂_nom > alpha by the full "
                         "batch), i.e. where the lemma's premise fails; in "
                         f"{fb} of them the selection also found no candidate below alpha at t "
                         f"or t+1, and {first} are at step 0 (the first call takes the real "
                         f"state by construction).", n > 0 and p == n))
        out.append(Claim(f"{n - p} of the {n} {t} failures with local constants occur with an "
                         f"admissible nominal state at {at}: {t} ({FORMS[t]}) fails with its "
                         "premise met.", n > p))
    for x in s.transition_failures:
        if x.test == "T3" and x.constants == "local" and x.n_failed:
            where = "at step 0" if x.last_step == 0 else f"in steps 0-{x.last_step}"
            out.append(Claim(f"Variance {_v(x.variance)}: all {x.n_failed} T3 failures (local "
                             f"constants) lie {where} of their episodes, at the start, far from "
                             "the goal.", x.last_step < 50))
    for e in s.t2e_failures:
        out.append(Claim(
            f"Variance {_v(e.variance)}: T2E fails at {e.n_failed} of {e.n_evaluated} steps, "
            f"{e.n_failed_R0} of them with R = 0, where the nominal state is the real one and "
            "both batches estimate the same free energy: there the two independent estimates "
            f"differ by a median of {e.gap_median:.3g}, more than 2Ê (median "
            f"{e.two_E_median:.3g}). With a median ESS of {e.ess_median:.3g} of N = "
            f"{s.config['n_samples']} samples the "
            "delta-method Ê does not cover the Monte Carlo error.",
            e.n_failed_R0 > 0 and e.gap_median > e.two_E_median))
    return out


def stratum_claims(s: BoundSummary) -> list[Claim]:
    out = []
    for v in s.variances:
        r = s.row("T1", "local", v.variance, "nominal_is_real")
        if r is not None:
            out.append(Claim(f"Variance {_v(v.variance)}: on the {r.n_steps} steps where the "
                             "nominal state was the real state, R = 0 and T1 holds with zero "
                             "slack (identical real and nominal samples).",
                             r.slack_q05 == 0.0 == r.slack_q95 and r.n_holding == r.n_steps))
    lo, hi = s.variances[0], s.variances[-1]
    for t in ("T3", "T3b"):
        a, b = s.row(t, "local", lo.variance), s.row(t, "local", hi.variance)
        if a and b and lo.variance != hi.variance:
            ra, rb = Rate(a.n_holding, a.n_steps), Rate(b.n_holding, b.n_steps)
            out.append(Claim(f"{t} holds less often at variance {_v(hi.variance)} than at "
                             f"{_v(lo.variance)} (disjoint 95% intervals).", rb.below(ra)))
    n_ok = sum(v.n_secant_ok for v in s.variances)
    n = sum(v.n_steps for v in s.variances)
    out.append(Claim(f"The secant check (secant slopes <= the gradient estimates) passed at "
                     f"every one of the {n} steps.", n_ok == n))
    out.append(Claim(f"The secant check failed at {n - n_ok} of {n} steps.", n_ok < n))
    return out


def all_claims(s: BoundSummary, no_barrier_L_q: float) -> dict[str, list[Claim]]:
    return {"holds": holds_claims(s), "safe_steps": safe_step_claims(s),
            "looseness": looseness_claims(s, no_barrier_L_q),
            "transitions": transition_claims(s), "strata": stratum_claims(s)}
