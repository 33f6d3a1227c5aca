"""Study configuration: frozen, validated at construction (errors name the field)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from workbench.validation import (
    MAX_BATCH,
    MAX_STEPS,
    MAX_TASKS,
    at_most,
    fail,
    flag,
    integer,
    one_of,
    real,
)

# the tests of assumptions §11.3 as workbench.bound.checks names them (T2E: independent batch,
# "true-F" form)
TESTS: tuple[str, ...] = ("T1", "T1s", "T2", "T2E", "T3", "T3b", "T3c", "T3d")
STEP_TESTS = ("T1", "T1s", "T2", "T2E")
CONSTANTS: tuple[str, ...] = ("local", "global", "sampled")  # sampled: assumptions §11.4
RESULT_VERSION = 4  # bump when the meaning of stored task results changes
MAX_GRID = 10**7  # points of the global-Lipschitz grid




@dataclass(frozen=True)
class StudyConfig:
    """Everything a run depends on ([A] values; assumptions §11-§12). Bad values raise
    ValueError naming the field. ``episodes`` SA-RMPPI episodes of up to ``steps`` plant steps
    (an episode stops at a crash) per velocity variance; the Lemma-1 checks at every step.

    kappa: the progress alpha rule's margin (AlphaRule(kind="progress", kappa)); n_samples,
    horizon: the SAIS batch (N, T); calibration_steps: the undisturbed alpha-calibration run;
    grid_*: the global-Lipschitz grid (workbench.bound.LipschitzGrid); independent: draw a second
    batch per step for T2E; z, n_q, space: workbench.bound.BoundConfig.

    Size limits (checked here): at most 10^7 tasks per run, 10^7 steps per episode or
    calibration run, n_samples * horizon * 2 <= 2^31, 10^7 grid points.
    """

    variances: tuple[float, ...] = (0.0, 10.0, 100.0)
    episodes: int = 3
    steps: int = 150
    seed: int = 2026
    tests: tuple[str, ...] = TESTS
    kappa: float = 0.1
    n_samples: int = 1024
    horizon: int = 100
    calibration_steps: int = 600
    grid_spacing: float = 0.1
    grid_rings: int = 25
    grid_angles: int = 360
    independent: bool = True
    z: float = 3.0
    n_q: str = "T"
    space: str = "physical"

    def __post_init__(self) -> None:
        v = self.variances
        if isinstance(v, str) or not hasattr(v, "__iter__") or len(v) == 0:
            raise fail("variances", v, "must be a non-empty sequence of numbers >= 0")
        vs = tuple(real(f"variances[{i}]", x, 0.0) for i, x in enumerate(v))
        if len(set(vs)) != len(vs):
            raise fail("variances", v, "must not repeat a value")
        object.__setattr__(self, "variances", tuple(sorted(vs)))
        for name, lo, hi in (("episodes", 1, MAX_TASKS), ("steps", 2, MAX_STEPS),
                             ("seed", 0, None), ("n_samples", 4, MAX_BATCH),
                             ("horizon", 2, MAX_BATCH), ("calibration_steps", 10, MAX_STEPS),
                             ("grid_rings", 1, MAX_GRID), ("grid_angles", 4, MAX_GRID)):
            object.__setattr__(self, name, integer(name, getattr(self, name), lo, hi))
        at_most("episodes", self.episodes, len(vs) * self.episodes, MAX_TASKS,
                "variances x episodes (tasks of a run)")
        at_most("n_samples", self.n_samples, self.n_samples * self.horizon * 2, MAX_BATCH,
                "n_samples * horizon * nu (entries of a sampled batch; nu = 2)")
        at_most("grid_rings", self.grid_rings, self.grid_rings * self.grid_angles, MAX_GRID,
                "grid_rings * grid_angles (points of the Lipschitz grid)")
        t = self.tests
        if isinstance(t, str) or not hasattr(t, "__iter__") or len(t) == 0:
            raise fail("tests", t, f"must be a non-empty subset of {TESTS}")
        for x in t:
            if x not in TESTS:
                raise fail("tests", x, f"unknown test; allowed values are {TESTS}")
        object.__setattr__(self, "tests", tuple(x for x in TESTS if x in t))
        object.__setattr__(self, "kappa", real("kappa", self.kappa, 0.0))
        object.__setattr__(self, "grid_spacing",
                           real("grid_spacing", self.grid_spacing, 0.0, strict=True))
        object.__setattr__(self, "z", real("z", self.z, 0.0, strict=True))
        object.__setattr__(self, "independent", flag("independent", self.independent))
        one_of("n_q", self.n_q, ("T", "T-1"))
        one_of("space", self.space, ("physical", "augmented"))

    def as_dict(self) -> dict:
        return asdict(self)

    def results_dict(self) -> dict:
        """The values results depend on (no test selection, no sizes)."""
        d = self.as_dict()
        for k in ("tests", "variances", "episodes", "steps"):
            d.pop(k)
        return d
