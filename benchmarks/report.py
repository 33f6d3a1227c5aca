"""``reports/bench/report.md``: the record table, where the time of the sampler batches goes
(against the C floor), the NLP baselines of BaS-iLQG, and the growth curves."""

from __future__ import annotations

import os

from benchmarks.floor import cpu_flags, cpu_model
from benchmarks.latency import markdown as latency_markdown


def _fmt(v, spec: str = ".3g") -> str:
    return "—" if v is None else format(v, spec)


def _notes(r: dict) -> list[str]:
    p = r.get("params", {})
    notes = []
    if r.get("skipped"):
        notes.append(f"skipped: {r['skipped']}")
    for key in ("goal_ratio", "goal_ms"):
        if p.get(key) is not None:
            notes.append(f"{key} {p[key]}")
    if p.get("goal_met") is not None and "goal_x_floor" not in p:
        notes.append("goal met" if p["goal_met"] else "goal not met")
    if isinstance(p.get("iterations"), dict):
        notes.append("iterations " + ", ".join(f"{k} {v}" for k, v in p["iterations"].items()))
    if p.get("threads") is not None:
        notes.append(f"threads {p['threads']}")
    if "x_floor" in p:
        n = f"{p['x_floor']:.2f}x floor"
        if p.get("goal_x_floor") is not None:
            n += (f" (goal <= {p['goal_x_floor']}x, "
                  f"{'met' if p.get('goal_met') else 'not met'})")
        notes.append(n)
    if "max_rel_cost_difference" in p:
        notes.append(f"objectives agree to {p['max_rel_cost_difference']:.1e}")
    if "max_rel_err_vs_kernel_on_kernel_noise" in p:
        notes.append(f"baseline = kernel to {p['max_rel_err_vs_kernel_on_kernel_noise']:.0e}")
    if "nlp_max_rel_cost_difference" in p:
        notes.append(f"IPOPT/FATROP objectives agree to {p['nlp_max_rel_cost_difference']:.1e}")
    if "slowdown_vs_di" in p:
        notes.append(f"slowdown {p['slowdown_vs_di']:.2f}x (goal <= {p['goal_slowdown']}x"
                     f"{', met' if p['goal_met'] else ', not met'}); same kernel with cubic "
                     f"polynomials for sin/cos: {p['floor_polynomial_unicycle_vs_di']:.2f}x")
    if "vector_vs_scalar_max_rel_diff" in p and "slowdown_vs_di" not in p:
        notes.append(f"{p['vector_math']}, <= {p['max_ulp_tested']} ulp; vector = scalar to "
                     f"{p['vector_vs_scalar_max_rel_diff']:.0e}")
    if "al_rel_cost_gap_vs_fatrop" in p:
        notes.append(f"AL cost gap {p['al_rel_cost_gap_vs_fatrop']:.1e}")
    return notes


def _by_name(records: list[dict]) -> dict[str, dict]:
    return {r["name"]: r for r in records}


def split_section(records: list[dict]) -> list[str]:
    """Table: each part of the SAIS and BaS-MPPI batches as ms and as a multiple of the floor."""
    rec = _by_name(records)
    parts = ("noise_generation", "rollout_given_noise", "python_call", "weights", "update")
    rows = []
    for kind, label in (("sais", "SAIS"), ("bas_mppi", "BaS-MPPI")):
        for th in (1, 2):
            suffix = f"N1024_T100_{th}thread"
            fl = rec.get(f"floor_{kind}_rollout_{suffix}")
            batch = rec.get(f"{kind}_batch_vs_floor_{suffix}")
            if fl is None or batch is None:
                continue
            cells = [f"{label}, {th} thread{'s' if th > 1 else ''}", f"{fl['value']:.3f}"]
            for part in parts:
                r = rec.get(f"{kind}_split_{part}_{suffix}")
                cells.append("—" if r is None else
                             f"{r['value']:.3f} ({r['params']['x_floor']:.2f}x)")
            xm = batch["params"].get("x_floor_min")
            cells.append(f"{batch['value']:.3f} (**{batch['params']['x_floor']:.2f}x**"
                         + ("" if xm is None else f"; minima {xm:.2f}x") + ")")
            rows.append("| " + " | ".join(cells) + " |")
    if not rows:
        return []
    sais1 = rec.get("sais_batch_vs_floor_N1024_T100_1thread")
    p = sais1["params"] if sais1 else {}
    out = ["", "## Where the time goes: the sampler batches against the C floor", "",
           "N = 1024, T = 100, the 30-circle map, float64. Floor: the hand-written C rollout "
           "(`benchmarks/floor/sais_floor.c`, 8 samples per AVX-512 block, noise given as an "
           "input array, same compiler and flags as the kernels), checked equal to the kernel "
           f"to {_fmt(p.get('max_rel_err_floor_vs_kernel'), '.0e')} per element. Parts (ms, and "
           "x floor): noise generation = seeded kernel - kernel reading the same noise; rollout "
           "= kernel reading the noise (dynamics, barrier, crash test, costs, applied controls); "
           "Python call = `Sampler` call - bare seeded kernel; weights = the importance "
           "weightings (NumPy); update = the weighted control sums. Batch = `Sampler` call + "
           "weights + update, timed as one piece. All timed in turn in one loop (medians).", "",
           "| batch | floor [ms] | noise generation | rollout | Python call | weights | update "
           "| whole batch (x floor) |", "|---|---:|---:|---:|---:|---:|---:|---:|", *rows]
    if sais1:
        met = "met" if p.get("goal_met") else "not met"
        out += ["", f"SAIS batch on 1 thread: {p['x_floor']:.2f}x the floor (goal <= "
                f"{p['goal_x_floor']}x: {met})."]
        ms = p.get("medians_ms", {})
        if "floor_group4" in ms:
            out.append(f"The floor with one division per four circles instead of per pair: "
                       f"{ms['floor_group4']:.3f} ms vs {ms['floor']:.3f} ms (divisions do "
                       f"{'not ' if ms['floor_group4'] >= 0.95 * ms['floor'] else ''}bound "
                       "the rollout). Stand-alone `lib.normals` (scalar generator, same "
                       f"draws): {ms.get('normals', float('nan')):.3f} ms.")
    seeded = rec.get("floor_sais_seeded_N1024_T100_1thread")
    if seeded:
        q = seeded["params"]
        out.append(f"The floor drawing the kernels' noise itself (the library's generator, 8 "
                   f"samples per block), 1 thread: {seeded['value']:.3f} ms = "
                   f"{q['x_floor']:.2f}x the floor, i.e. {q['noise_generation_in_floor_ms']:.3f} "
                   f"ms of generation; that generator alone: {q['floor_normals_ms']:.3f} ms.")
    l4 = rec.get("floor_sais_4lanes_vs_8lanes_N1024_T100_1thread")
    if l4:
        out.append(f"The floor with 4 samples per block (the kernels' block width) instead of "
                   f"8, 1 thread: {l4['value']:.3f} ms = {l4['params']['x_floor']:.2f}x the "
                   "floor.")
    steps = [r for r in records if r["name"].startswith("sa_rmppi_step_vs_floor")]
    for r in steps:
        sp = r["params"]
        split = ", ".join(f"{k} {v:.3f} ms" for k, v in sp["split_median_ms"].items())
        out.append(f"SA-RMPPI step, {sp['threads']} thread(s): {r['value']:.3f} ms = "
                   f"{sp['x_floor']:.2f}x the floor ({split}).")
    return out


def nlp_section(records: list[dict]) -> list[str]:
    """BaS-iLQG (both variants) against IPOPT and FATROP, VM and jit."""
    r = next((x for x in records if x["name"].startswith("bas_ilqg_ddp_vs_")), None)
    if r is None:
        return []
    p = r["params"]
    ms, costs = p.get("solve_ms", {}), p.get("costs", {})
    d = p.get("rel_cost_difference_vs_ipopt", {})
    du = p.get("max_abs_control_difference_vs_ipopt", {})
    it = p.get("iterations", {})
    out = ["", "## BaS-iLQG against the strongest NLP baselines (tracking, T = 150)", "",
           "Same multiple-shooting NLP for IPOPT and FATROP (FATROP with structure detection); "
           "`_jit`: CasADi's jit of the NLP functions (cached after the first build), else "
           "CasADi's virtual machine. Solver call only; medians.", "",
           "| solver | solve [ms] | iterations | cost | rel. cost diff. vs IPOPT | "
           "max abs control diff. vs IPOPT |", "|---|---:|---:|---:|---:|---:|"]
    for n in ms:
        out.append(f"| {n} | {ms[n]:.2f} | {it.get(n, '—')} | {costs.get(n, float('nan')):.9g} | "
                   f"{_fmt(d.get(n), '.1e')} | {_fmt(du.get(n), '.1e')} |")
    v = p.get("variant", {})
    if v:
        fj = ms.get("fatrop_jit")
        ratio = "" if fj is None else (
            f"; {v['faster_variant']} is {fj / ms[v['faster_variant']]:.1f}x FATROP-jit, "
            f"{v['library_default']} (library default) "
            f"{fj / ms[v['library_default']]:.1f}x")
        out += ["", f"Faster iLQG variant: **{v['faster_variant']}** "
                f"({v['speedup_of_faster']:.2f}x the other), agrees with IPOPT to 1e-6: "
                f"{v['faster_agrees_with_ipopt_1e-6']}; library default: "
                f"{v['library_default']}; recommended default: "
                f"**{v['recommended_default']}**{ratio}."]
    return out


def _yes(ok: bool) -> str:
    return "met" if ok else "**not met**"


FLOOR_EXTRAS = ("noise_generation", "python_call", "weights", "update")


def _floor_bound(rec: dict, r: dict, measured: float) -> str:
    """The least batch / floor ratio: the floor computes the rollout alone (noise given), the
    batch also draws its noise, crosses the Python call and weights and updates: each part as
    the split timed it in this run, the rollout itself free beyond the floor."""
    parts = [rec.get(f"sais_split_{k}_N1024_T100_1thread") for k in FLOOR_EXTRAS]
    floor = r.get("baseline_value")
    if not floor or not all(q and q.get("value") is not None for q in parts):
        return ""
    extra = sum(q["value"] for q in parts)
    lb = (floor + extra) / floor
    if lb > measured + 1e-9:
        return (f"measured below the {lb:.2f} of the floor plus the split's other parts: no "
                "bound rules the goal out")
    return (f"at least {lb:.2f}: the floor plus the parts it does not compute (noise "
            f"{parts[0]['value']:.2f} ms, Python call {parts[1]['value']:.2f} ms, weights and "
            f"update {parts[2]['value'] + parts[3]['value']:.2f} ms) on a {floor:.2f} ms floor")


def goals_section(records: list[dict]) -> list[str]:
    """The performance goals against this run's figures, with the bound that limits a goal
    this design cannot reach (each figure is a ratio measured in the same loop)."""
    rec = _by_name(records)
    rows = []
    r = rec.get("sais_batch_vs_floor_N1024_T100_1thread")
    if r:
        p = r["params"]
        rows.append(f"| SAIS batch, 1 thread, x hand-written C floor | <= {p['goal_x_floor']} "
                    f"| {p['x_floor']:.2f} | {_yes(p['x_floor'] <= p['goal_x_floor'])} | "
                    f"{_floor_bound(rec, r, p['x_floor'])} |")
    r = rec.get("sais_batch_N1024_T100_1thread_float32")
    if r and r.get("ratio"):
        p = r["params"]
        bound = ""
        if p.get("kernel64_ms") and p.get("kernel32_ms"):
            # everything outside the kernel (the noise, drawn in double in both precisions for
            # pairing, the Python call, the guards) as in float64, the kernel at its measured
            # float32 speed-up: all from the same alternated calls of this record
            t64, k64, k32 = r["baseline_value"], p["kernel64_ms"], p["kernel32_ms"]
            est = t64 / (t64 - k64 + k32)
            if est + 1e-9 >= r["ratio"]:
                bound = (f"at most {est:.2f}: the call outside the kernel ({t64 - k64:.2f} ms "
                         f"of {t64:.2f}) unchanged and the kernel at its measured "
                         f"{k64 / k32:.2f}x")
            else:
                bound = (f"measured above the {est:.2f} of the call outside the kernel "
                         "unchanged: no bound rules the goal out")
        alt = p.get("alternated_ratio")
        alt_txt = "" if alt is None else f"; call by call in alternation {alt:.2f}"
        rows.append(f"| float32 SAIS batch speed-up, 1 thread | >= {p['goal_ratio']} | "
                    f"{r['ratio']:.2f} (kernel alone {p['kernel_ratio']:.2f}{alt_txt}) | "
                    f"{_yes(r['ratio'] >= p['goal_ratio'])} | {bound} |")
    r = rec.get("sa_rmppi_step_over_sais_batch_N1024_T100_2thread")
    if r:
        p = r["params"]
        lb = p.get("lower_bound_step_over_batch")
        bound = ("" if lb is None else f"at least {lb:.2f}: the batch plus the candidate "
                 f"batch ({p['candidates']} rollouts of the whole horizon), everything else "
                 "free")
        if lb is not None and lb > p["step_over_batch"] + 1e-9:  # contradicted: not a bound
            bound = (f"measured below the {lb:.2f} of the batch plus the candidate batch: no "
                     "bound rules the goal out")
        rows.append(f"| SA-RMPPI step / its SAIS batch, 2 threads | <= "
                    f"{p['goal_step_over_batch']} | {p['step_over_batch']:.2f} | "
                    f"{_yes(p['step_over_batch'] <= p['goal_step_over_batch'])} | {bound} |")
    r = rec.get("threads_sa_rmppi_step_passive_adaptive_load2")
    if r and r.get("value"):
        x = r["value"] / r["baseline_value"]
        goal = 1 / r["params"]["goal_ratio"]
        rows.append(f"| 2-thread / 1-thread SA-RMPPI step under a load of 2 | <= {goal:.2f} "
                    f"| {x:.2f} | {_yes(x <= goal + 1e-9)} | |")
    r = rec.get("bas_ilqg_default_vs_fatrop_jit_tracking_T150")
    if r and r.get("ratio"):
        d = r["params"].get("max_rel_cost_difference")
        agree = "" if d is None else f"; costs agree to {d:.1e} (goal 1e-6)"
        ok = r["ratio"] >= 10 and (d is None or d <= 1e-6)
        rows.append(f"| BaS-iLQG (default) speed-up over FATROP with jit | >= 10 | "
                    f"{r['ratio']:.1f}{agree} | {_yes(ok)} | |")
    if not rows:
        return []
    return ["", "## Performance goals in this run", "",
            "| goal | target | measured | | what bounds it |", "|---|---:|---:|---|---|",
            *rows]


def report_markdown(records: list[dict], man: dict, growth_md: str | None = None) -> str:
    """The whole report: every ratio is baseline_value / value, both measured in this run."""
    flags = cpu_flags()
    have = ", ".join(k for k in ("avx2", "avx512f") if flags.get(k)) or "no AVX2/AVX-512"
    lines = ["# Benchmarks (`make bench`)", "",
             "Medians of repeats in one process; every ratio = baseline / value, both measured "
             "in this run (alternating where both are timed in a loop). Machine: "
             f"{cpu_model()} ({have}), {man.get('platform', '?')}, {os.cpu_count()} CPUs; "
             f"git {str(man.get('git_revision', '?'))[:10]}.", "",
             "| benchmark | value | unit | baseline | baseline value | ratio | notes |",
             "|---|---:|---|---|---:|---:|---|"]
    goals = goals_section(records)
    if goals:
        lines[-2:-2] = [*goals[1:], "", "## Every record", ""]
    for r in records:
        lines.append(f"| {r['name']} | {_fmt(r['value'])} | {r['unit']} | "
                     f"{r['baseline'] or '—'} | {_fmt(r['baseline_value'])} | "
                     f"{_fmt(r['ratio'], '.1f')} | {'; '.join(_notes(r))} |")
    lines += split_section(records)
    lines += latency_markdown(records)
    lines += nlp_section(records)
    if growth_md:
        lines += ["", growth_md.rstrip()]
    return "\n".join(lines) + "\n"
