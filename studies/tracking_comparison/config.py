"""Study configuration: frozen, validated at construction (errors name the field)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from workbench.validation import MAX_TASKS, at_most, fail, flag, integer, one_of, real

METHODS: tuple[str, ...] = ("ecbf", "al", "bas")
RESULT_VERSION = 2  # bump when the meaning of stored task results changes
MAX_ROLLOUTS = 10**6  # rollouts of one task (n_rollouts, sweep_rollouts)
SWEPT = ("q_beta", "pole", "q_scale", "ecbf_noise", "noise_std")
NOISE_PLACEMENTS = ("before", "after")
# the swept values each method's results depend on
RELEVANT = {"ecbf": ("pole", "q_scale", "ecbf_noise", "noise_std"),
            "al": ("q_scale", "noise_std"), "bas": ("q_beta", "q_scale", "noise_std")}




def _values(name: str, values, *, strict: bool = True) -> tuple[float, ...]:
    if isinstance(values, str) or not hasattr(values, "__iter__") or len(values) == 0:
        raise fail(name, values, "must be a non-empty sequence of numbers")
    return tuple(real(f"{name}[{i}]", v, 0.0, strict=strict) for i, v in enumerate(values))


@dataclass(frozen=True)
class Variant:
    """The [A] values a run depends on (assumptions §15), swept by the sensitivity study.

    q_beta: BaS barrier-state weight; pole: ECBF poles p1 = p2 = pole; q_scale: factor on the
    tracking weight Q = diag(10, 10, 1, 1) (R and S unchanged); ecbf_noise: whether the control
    noise enters before the ECBF filter (the default, assumptions §6.3) or after it
    (assumptions §13 E7); noise_std: control-noise standard deviation (paper [P]: 10).
    """

    q_beta: float = 1e-2
    pole: float = 5.0
    q_scale: float = 1.0
    ecbf_noise: str = "before"
    noise_std: float = 10.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "q_beta", real("q_beta", self.q_beta, 0.0, strict=False))
        object.__setattr__(self, "pole", real("pole", self.pole, 0.0, strict=True))
        object.__setattr__(self, "q_scale", real("q_scale", self.q_scale, 0.0, strict=True))
        one_of("ecbf_noise", self.ecbf_noise, NOISE_PLACEMENTS)
        object.__setattr__(self, "noise_std", real("noise_std", self.noise_std, 0.0, strict=False))

    def relevant(self, method: str) -> dict[str, float | str]:
        """The values that change a method's results."""
        return {k: getattr(self, k) for k in RELEVANT[method]}

    def for_method(self, method: str, base: Variant) -> Variant:
        """This variant with the values ``method`` does not depend on set to ``base``'s, so
        that points of the sweep that cannot change a method share its tasks."""
        return replace(base, **self.relevant(method))


@dataclass(frozen=True)
class StudyConfig:
    """Everything a run depends on; the defaults are the full profile, the profile files
    (``quick.toml``, ``paper.toml``, ``full.toml``) set the sizes. Bad values raise ValueError
    naming the field.

    Main study: n_seeds x n_rollouts per method at ``base``. Sweep: for each [A] parameter and each
    of its values (others at base), sweep_seeds x sweep_rollouts per method. failure = unsafe or
    final distance > target_radius [A]; ``radii``: the success radii of the radius sweep
    (computed from the same rollouts).

    Size limits (checked here): at most 10^7 tasks per run and 10^6 rollouts per task.
    """

    methods: tuple[str, ...] = METHODS
    n_rollouts: int = 500
    n_seeds: int = 10
    seed: int = 2022
    target_radius: float = 0.5
    radii: tuple[float, ...] = (0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)
    base: Variant = field(default_factory=Variant)
    sweep: bool = True
    sweep_q_beta: tuple[float, ...] = (1e-3, 1e-2, 1e-1, 1.0)
    sweep_pole: tuple[float, ...] = (2.0, 5.0, 10.0)
    sweep_q_scale: tuple[float, ...] = (0.1, 1.0, 10.0)
    sweep_ecbf_noise: tuple[str, ...] = NOISE_PLACEMENTS
    sweep_noise_std: tuple[float, ...] = (5.0, 10.0, 15.0)
    sweep_rollouts: int = 250
    sweep_seeds: int = 2

    def __post_init__(self) -> None:
        methods = self.methods
        if isinstance(methods, str) or not hasattr(methods, "__iter__") or len(methods) == 0:
            raise fail("methods", methods, f"must be a non-empty subset of {METHODS}")
        for m in methods:
            if m not in METHODS:
                raise fail("methods", m, f"unknown method; allowed values are {METHODS}")
        if len(set(methods)) != len(methods):
            raise fail("methods", methods, "must not repeat a method")
        object.__setattr__(self, "methods", tuple(m for m in METHODS if m in methods))
        object.__setattr__(self, "n_rollouts",
                           integer("n_rollouts", self.n_rollouts, 1, MAX_ROLLOUTS))
        object.__setattr__(self, "n_seeds", integer("n_seeds", self.n_seeds, 1, MAX_TASKS))
        object.__setattr__(self, "seed", integer("seed", self.seed, 0))
        object.__setattr__(self, "target_radius",
                           real("target_radius", self.target_radius, 0.0, strict=True))
        object.__setattr__(self, "radii", tuple(sorted(_values("radii", self.radii))))
        if not isinstance(self.base, Variant):
            raise fail("base", self.base, "must be a Variant")
        for name in ("q_beta", "pole", "q_scale", "noise_std"):
            object.__setattr__(self, f"sweep_{name}", _values(
                f"sweep_{name}", getattr(self, f"sweep_{name}"),
                strict=name not in ("q_beta", "noise_std")))
        placements = self.sweep_ecbf_noise
        if isinstance(placements, str) or len(placements) == 0 or any(
                p not in NOISE_PLACEMENTS for p in placements):
            raise fail("sweep_ecbf_noise", placements, f"must be a non-empty subset of "
                       f"{NOISE_PLACEMENTS}")
        object.__setattr__(self, "sweep_ecbf_noise", tuple(placements))
        object.__setattr__(self, "sweep_rollouts",
                           integer("sweep_rollouts", self.sweep_rollouts, 1, MAX_ROLLOUTS))
        object.__setattr__(self, "sweep_seeds",
                           integer("sweep_seeds", self.sweep_seeds, 1, MAX_TASKS))
        object.__setattr__(self, "sweep", flag("sweep", self.sweep))
        points = sum(len(getattr(self, f"sweep_{name}")) for name in SWEPT) if self.sweep else 0
        main, swept = self.n_seeds, points * self.sweep_seeds
        big = "n_seeds" if main >= swept else "sweep_seeds"
        at_most(big, getattr(self, big), len(self.methods) * (1 + main + swept), MAX_TASKS,
                "methods x (1 + n_seeds + sweep points x sweep_seeds) (tasks of a run, at most)")

    def sweep_points(self) -> list[tuple[str, float | str, Variant]]:
        """(parameter, value, variant) for every swept value, the others at base."""
        if not self.sweep:
            return []
        return [(name, v, replace(self.base, **{name: v}))
                for name in SWEPT for v in getattr(self, f"sweep_{name}")]

    @property
    def noise_std(self) -> float:
        return self.base.noise_std

    def as_dict(self) -> dict:
        return asdict(self)
