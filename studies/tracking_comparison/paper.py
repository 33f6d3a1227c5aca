"""What the paper reports [P] (assumptions §14.1), the reproduction bands [A] (assumptions
§14.4), every assumed value a run uses ([A], assumptions §15), and whether a run's set-up is the
paper's (:func:`comparison`), in one place."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from studies.tracking_comparison.config import StudyConfig
from studies.tracking_comparison.methods import Setup
from studies.tracking_comparison.wording import NAMES
from workbench.study.report import Provenance, not_compared_row, run_provenance
from workbench.study.spec import PaperRow


@dataclass(frozen=True)
class PaperFigure:
    """One number of the paper: the metric it is a rate of, its value, the reproduction band
    (assumptions §14.4)."""

    method: str
    metric: str  # "unsafe" or "failure"
    value: float
    band: tuple[float, float]
    text: str


PAPER = (
    PaperFigure("ecbf", "failure", 0.27, (0.15, 0.40),
                "≈27% of MC samples fail (unsafe or not at the target)"),
    PaperFigure("al", "unsafe", 0.60, (0.40, 0.80), "≈60% of MC trajectories unsafe"),
    PaperFigure("bas", "unsafe", 0.0, (0.0, 0.01), "0 violations in 500 MC samples"),
)
PAPER_BY_METHOD = {p.method: p for p in PAPER}
# the paper's ranking (safest first) implied by its numbers
PAPER_ORDER = ("bas", "ecbf", "al")
# [A] thresholds used by the findings
TOUCH_TOLERANCE = 1e-3  # |closed-loop min h| below this [m^2]: the nominal touches the obstacle


def assumed_values(config: StudyConfig, setup: Setup) -> list[dict[str, str]]:
    """Every value the run used that the paper does not give ([A]) or takes from elsewhere."""
    sc, w, b, e, a, i = setup.scene, setup.weights, setup.barrier, setup.ecbf, setup.al, \
        setup.ilqg
    rows = [
        ("start, target", f"{sc.start}, {sc.target}", "A (assumptions §3.3)"),
        ("obstacle", f"centre {sc.obstacle.center}, radius {sc.obstacle.radius} m",
         "A (assumptions §3.3)"),
        ("reference", "straight line start -> target at constant speed over N dt "
         "(10/3 m/s), through the obstacle", "A (assumptions §3.3)"),
        ("horizon N, dt", f"{sc.horizon}, {sc.dt} s", "A (assumptions §2.5)"),
        ("model", "planar double integrator, explicit Euler; h = ‖p − c‖² − r²",
         "A / X (assumptions §2, §3.1)"),
        ("control box", f"+-{sc.u_limit} per axis", "P"),
        ("control noise", f"N(0, {config.noise_std:g}^2 I) i.i.d. per step (swept: "
         f"{config.sweep_noise_std}); "
         f"{config.base.ecbf_noise} the ECBF filter; inside the clip for AL and BaS",
         "P (std) / A (where, assumptions §13 E7)"),
        ("Monte Carlo size", f"{config.n_seeds} seeds x {config.n_rollouts} rollouts per method",
         "P (500, BaS) / A (others, seeds)"),
        ("tracking weights", f"Q = {config.base.q_scale:g} x diag{w.Q}, R = diag{w.R}, "
         f"S = diag{w.S}", "A (assumptions §6)"),
        ("BaS barrier", f"{b.kind} 1/h, one summed state, gamma = {b.gamma}, crash at "
         f"h <= {b.eps_h:g} -> beta = {b.beta_max:g}", "X (DBaS-code) / A"),
        ("BaS weights", f"q_beta = {config.base.q_beta:g} (swept), s_beta = {w.s_beta}, "
         f"cost on (beta - beta_target)^2", "A / X (assumptions §4.5, §6.1)"),
        ("iLQG", f"mu0 = {i.mu_init}, factor {i.mu_factor}, tol_rel = {i.tol_rel:g}, "
         f"max_iter = {i.max_iter}, box QP, U0 = 0", "X / A (assumptions §5)"),
        ("AL-iLQG", f"lambda0 = {a.lambda_init:g}, mu0 = {a.mu_init:g}, phi = {a.phi:g}, "
         f"tau = {a.tau:g}, mu_max = {a.mu_max:g}, eps_c = {a.constraint_tol:g} m^2, "
         f"<= {a.max_outer} outer, {a.mu_update} mu update, Gauss-Newton, inner tol_rel = "
         f"{a.inner.tol_rel:g}", "A / X (assumptions §6.2, ALTRO)"),
        ("ECBF poles", f"p1 = p2 = {config.base.pole:g} (k1 = p1 + p2, k0 = p1 p2), swept",
         "A (assumptions §7.1)"),
        ("ECBF QP", f"{e.mode} rows normalised to ‖a_i‖ = 1, slack cost {e.slack_linear:g} "
         f"delta + {e.slack_quadratic:g} delta^2 (assumptions §7.2: 1e6 delta^2), infeasible if "
         f"delta > {e.slack_tol:g}; OSQP eps {e.eps_abs:g}, polish {e.polish}, warm start",
         "A (deviation, see workbench/filters/ecbf.py) / assumptions §7.2"),
        ("ECBF nominal", "plain iLQG on the tracking problem without the obstacle",
         "P / assumptions §6.3"),
        ("unsafe", "min over k = 0..N and obstacles of h(x_k) < 0", "assumptions §6.4"),
        ("failure", f"unsafe or ‖p_N − p_target‖ > {config.target_radius:g} m (success radius "
         f"swept over {config.radii} m on the same rollouts)", "A (assumptions §6.4)"),
        ("randomness", f"root seed {config.seed}; SeedSequence(root, spawn_key=(method, seed))"
         " per task", "A"),
        ("sweep", f"q_beta in {config.sweep_q_beta}, poles in {config.sweep_pole}, Q scale in "
         f"{config.sweep_q_scale}, ECBF noise {config.sweep_ecbf_noise} the filter; "
         f"{config.sweep_seeds} seeds x {config.sweep_rollouts} "
         "rollouts (same noise prefix as the main seeds)", "A"),
    ]
    return [{"name": n, "value": v, "source": src} for n, v, src in rows]


# keys whose change keeps the paper's rates comparable: counts, seeds, methods and sweeps
SIZES = ("methods", "n_rollouts", "n_seeds", "seed", "radii", "sweep", "sweep_q_beta",
         "sweep_pole", "sweep_q_scale", "sweep_ecbf_noise", "sweep_noise_std", "sweep_rollouts",
         "sweep_seeds")
NOT_COMPARABLE = "the paper's Monte Carlo rates"


def comparison(config: StudyConfig, out: Path | None = None) -> Provenance:
    """Whether a run's set-up is the paper's (the ``paper`` profile up to :data:`SIZES`): a
    changed noise level, weight, pole or success radius makes it a custom run."""
    from studies.tracking_comparison import STUDY
    from workbench.study.report import provenance

    return provenance(STUDY, config, out, SIZES)


def paper_rows(out: Path) -> list[PaperRow]:
    """The paper's rates beside this run's, for the report site; one row saying so for a
    custom run."""
    import json

    from studies.tracking_comparison import STUDY

    skip = not_compared_row(run_provenance(STUDY, out, SIZES), "Sec. III rates",
                            NOT_COMPARABLE)
    if skip is not None:
        return [skip]
    summary = json.loads((Path(out) / "summary.json").read_text())
    ours = {m["method"]: m for m in summary["methods"]}
    rows = []
    for p in PAPER:
        if p.method not in ours:
            continue
        r = ours[p.method][p.metric]
        inside = p.band[0] <= r["value"] <= p.band[1]
        rows.append(PaperRow(
            f"{NAMES[p.method]}: {p.metric} rate", f"{p.value:.0%} ({p.text})",
            f"{r['value']:.1%} [{r['low']:.1%}, {r['high']:.1%}], n = {r['n']}",
            f"band {p.band[0]:.0%}-{p.band[1]:.0%} (assumptions §14.4): "
            f"{'inside' if inside else 'outside'}"))
    return rows
