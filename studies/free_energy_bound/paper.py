"""Lemma 1 as printed [P], the reading this study uses (assumptions §11, §13 L1-L5 and the
resolutions in workbench.bound), the [A] thresholds the findings use, and every assumed value of
a run."""

from __future__ import annotations

from studies.free_energy_bound.config import StudyConfig
from studies.free_energy_bound.shared import Shared
from workbench.sampling.threshold import AlphaRule

LEMMA = r"""Let $\mathcal{F}_{MC}(S,\mathbb{P},x_0,\lambda)$ be the estimate of the free energy of
the real system, $\mathcal{F}_{MC}(S,\mathbb{P},x_0^*,\lambda)$ that of the nominal system, and
$E_M^V$ the upper bound on the uncertainty of the free-energy estimates. Given a nominal control
sequence $u^*$, let $\mathcal{B}$ be a tube of radius $R$ about the nominal trajectory and
$\mathcal{C}^* = \mathcal{B} \cup \mathcal{C}$. Let $L_q$, $L_\phi$ be the Lipschitz constants of
$q$ and $\phi$ in $\mathcal{C}^*$, $D_F(x_0, x_0^*, u) = \|F(x_0,u)-x_0\| + \|x_0^*-x_0\| + D$,
and assume a safe controller $K_{safe}$ renders the real dynamics controlled forward invariant
w.r.t. $\mathcal{C}^*$. Then

$$\Delta\mathcal{F}_{MC}(S,\mathbb{P},x_0,\lambda) \le
\big(\alpha-\mathcal{F}_{MC}(S,\mathbb{P},x_0^*,\lambda)\big) + 2E_M^V
+ \big(R(L_\phi + (T-1)L_q\big)D_F(x_0,x_0^*,u).$$

(The paper's Lemma 1, parenthesis as printed; its proof's step is
$S(V,x_0) \le S(V,x_0^*) + \delta$, $\delta = (L_\phi + (T-1)L_q)R$.)"""

READING = (
    "L1: $\\mathcal{C}^* = \\mathcal{B} \\cap \\mathcal{C}$ (a union is not local): the local "
    "constants are maxima of $\\|\\nabla q\\|$, $\\|\\nabla\\phi\\|$ at 5 points on each segment "
    "from a nominal sample's state to its real sample's state ($s \\in \\{0, .25, .5, .75, 1\\}$, "
    "all samples, $k = 1..T$ for $q$, $k = T$ for $\\phi$); points with $\\min h \\le 0$ are "
    "excluded and counted. The global constants are the maxima over a grid of the whole map "
    "(below), the closest ring at $h = 2\\epsilon_h$.",
    "L2: the printed bound (T3) multiplies the Lipschitz term by $D_F$; the proof's $\\delta$ has "
    "no $D_F$ factor (T3b). Both are tested.",
    "L3: $\\Delta\\mathcal{F}_{MC} = \\hat F_{real}(t+1) - \\hat F_{real}(t)$ over consecutive "
    "plant steps, each $\\hat F$ the log-sum-exp of the pure state costs plus the likelihood "
    "ratio over the step's first SAIS batch (assumptions §11.2, item 3); $E_M^V$ = delta "
    "method, z = 3, max over real and nominal and over t, t+1 (assumptions §11.2, item 4); "
    "$\\alpha$ = the threshold at step t's chosen nominal state (T3d: at t+1).",
    "Norm: R, the Lipschitz constants and $D_F$ on the physical state (p, v); $q$ depends on "
    "$\\beta$, but on every sample $\\beta_k = B(h(p_k))$, so $q(\\bar x) = \\tilde q(x) = "
    "q(lift(x))$ and $\\nabla\\tilde q$ includes the barrier term "
    "$2 q_\\beta (\\beta-\\beta_g) \\sum_i B'(h_i) \\nabla h_i$ (assumptions §11.2, items 5-6).",
    "L4: $n_q$ = T running terms (Algorithm 1 sums T; the lemma's T-1 does not follow from the "
    "tube argument with the sums as implemented). L5: D = the 99.9 % quantile of the "
    "disturbance's norm per step.",
    "T1 (per sample, all n): $S^x_n \\le S^{x*}_n + \\delta_t$; T1s: T1 over the samples whose "
    "real and nominal rollouts both stayed safe; T2: $\\hat F_{real}(t) \\le \\hat F_{nom}(t) + "
    "\\delta_t$; T2E: T2 against $\\hat F_{nom}$ of an independent batch of the same step, "
    "$+2\\hat E$; T3: as printed; T3b: without $D_F$; T3c: $\\hat F_{nom}(t+1)$ in place of "
    "$\\hat F_{nom}(t)$; T3d: $\\hat F_{real}(t+1) \\le \\alpha_{t+1} + \\delta_{t+1} + 2\\hat E$.",
)

# [A] thresholds used by the findings
LOOSE_FACTOR = 10.0  # the bound is "loose" when median δ_local exceeds median |F̂_real| by this
USEFUL_LOCALISATION = 100.0  # global/local Lipschitz-term ratio that would be a real gain


def assumed_values(config: StudyConfig, shared: Shared) -> list[dict[str, str]]:
    """Every value of the run the paper does not give ([A])."""
    c = config
    return [
        {"name": "alpha rule", "value": f"progress, kappa = {c.kappa:g} (alpha = (1 + kappa) x "
         f"undisturbed free energy at the distance to the goal; {c.calibration_steps} "
         "calibration steps)", "source": "[A] kappa = 0.1 from an activation sweep on this map; "
         f"note: AlphaRule() in the code defaults to kappa = {AlphaRule().kappa:g}"},
        {"name": "SAIS batch", "value": f"N = {c.n_samples}, T = {c.horizon}, sigma = (5, 5), "
         "lambda = 10, q_beta = 0.01", "source": "[A] workbench.scenarios.navigation"},
        {"name": "episodes", "value": f"{c.episodes} per variance, up to {c.steps} steps "
         "(stop at a crash)", "source": "[A]"},
        {"name": "E_M^V", "value": f"delta method, z = {c.z:g}", "source": "[A] assumptions §11.2"},
        {"name": "n_q", "value": c.n_q, "source": "[A] assumptions §13 L4"},
        {"name": "norm", "value": c.space, "source": "[A] assumptions §11.2, item 5"},
        {"name": "T2E", "value": "independent batch per step" if c.independent else "off",
         "source": "assumptions §11.3"},
        {"name": "global grid", "value": shared.grid, "source": "[A] workbench.bound"},
    ]

VARIANT = "\n".join((
    r"**Lemma 1' (the sampled-tube bound).** For sample $n$ of a batch let "
    r"$e_{nk} = x^n_k - x^{*n}_k$ and let $G^q_{nk}$, $G^\phi_{nT}$ be the largest "
    r"$\|\nabla\tilde q\|$, $\|\nabla\tilde\phi\|$ on the segment from $x^{*n}_k$ to $x^n_k$. "
    r"With $\delta_n = \sum_{k=1}^{T} G^q_{nk}\|e_{nk}\| + G^\phi_{nT}\|e_{nT}\|$ and the "
    r"nominal batch's weights $w^*_n \propto \exp(-S^*_n/\lambda)$,",
    "",
    r"$$S_n \le S^*_n + \delta_n \ \text{for every } n, \qquad \hat F_{real} \le \hat F_{nom} + "
    r"\delta_\lambda, \quad \delta_\lambda = -\lambda \log \sum_n w^*_n e^{-\delta_n/\lambda} "
    r"\le \sum_n w^*_n \delta_n \le \max_n \delta_n \le (L_\phi + T L_q) R .$$",
    "",
    r"**Derivation.** (i) On each segment the mean-value theorem gives "
    r"$|q(x^n_k) - q(x^{*n}_k)| \le G^q_{nk}\|e_{nk}\|$ (and likewise for $\phi$); summing over "
    r"the $T$ running terms and the terminal term gives $S_n - S^*_n \le \delta_n$ (the "
    r"likelihood ratio is the same for both systems, so it cancels). (ii) "
    r"$\hat F(S) = -\lambda\log\frac1N\sum_n e^{-S_n/\lambda}$ is increasing in every $S_n$, so "
    r"$\hat F_{real} \le \hat F(S^* + \delta) = \hat F_{nom} - \lambda\log\sum_n w^*_n "
    r"e^{-\delta_n/\lambda}$. (iii) By Jensen's inequality ($e^{-x}$ is convex) the last term is "
    r"at most $\sum_n w^*_n\delta_n$, and each $\delta_n \le (L_\phi + T L_q) R$ because "
    r"$G_{nk} \le L$ and $\|e_{nk}\| \le R$: the variant is never looser than the proof's "
    r"$\delta$. The checks T1-T3d are repeated with $\delta_\lambda$ in place of $\delta$ (T1, "
    r"T1s: $\max_n \delta_n$ bounds the largest per-sample gap); as for the local constants, "
    "the segment maxima are taken at five points per segment, points inside obstacles "
    "excluded. It localises twice: per segment rather than over the tube, and weighted by the "
    "samples that carry the free energy rather than by the worst one.",
))
