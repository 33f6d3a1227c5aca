"""What automatic tuning may change per controller, how tuned values enter a controller's
settings, and the tuned defaults shipped for each (controller, system) pair.

Every controller tunes the sampler's exploration and temperature (``sigma_scale`` multiplies
the system's per-control sigma; ``lam``); the robust ones also the alpha rule's ``kappa``; a
method with a gain of its own tunes that gain too. The barrier-state weight ``q_beta`` is not
tuned: it is compiled into the sampling kernels, so each value would cost a compile.

The shipped defaults (``tuned.json`` beside this module) are written by the arena's tuning run
(``make tune-arena``). Each entry carries its provenance: the maps (family and seeds) it was
trained and validated on, the disturbance, the hash of the system's definition it was tuned on
(:func:`~workbench.scenarios.systems.definition_hash`), the budget, the objective, the training
and validation scores of the hand-tuned and the tuned point, and which of the two was kept
(``params``). :func:`shipped` reads them (format :data:`FORMAT` only: an older or damaged file is
refused, naming it); :func:`check_usable` refuses an entry for an evaluation whose test maps
overlap the maps it was tuned or validated on, one tuned without validation, and one tuned on
another definition of its system (or on an unrecorded one).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cache
from numbers import Integral, Real
from pathlib import Path

from workbench.sampling.mppi import MPPIConfig
from workbench.sampling.threshold import AlphaRule
from workbench.scenarios.methods import MethodSettings, method
from workbench.scenarios.systems import definition_hash
from workbench.study.tuning import Param, TuningBudget
from workbench.validation import fail

SHIPPED = Path(__file__).with_name("tuned.json")
FORMAT = 3  # the version of tuned.json this module reads and writes
KEPT = ("tuned", "hand")
RERUN = "rerun `make tune-arena`"

COMMON = (Param("sigma_scale", 0.25, 4.0), Param("lam", 0.3, 100.0))
KAPPA = Param("kappa", 0.01, 1.0)


def space(controller: str) -> tuple[Param, ...]:
    """The parameters tuning may change for ``controller``: :data:`COMMON`, :data:`KAPPA` for
    a robust method, and the method's own (:attr:`MethodSpec.tunable`)."""
    spec = method(controller)
    return COMMON + ((KAPPA,) if spec.robust else ()) + spec.tunable


@dataclass(frozen=True)
class ControllerSettings:
    """A controller's settings on one system: the sampler, the barrier-state weight, the
    alpha rule (robust controllers) and each method's own options."""

    sampler: MPPIConfig
    q_beta: float
    rule: AlphaRule
    methods: MethodSettings

    def values(self, controller: str) -> dict[str, float]:
        """The current values of ``space(controller)`` (sigma_scale relative to ``base``
        sigma is 1 by definition: the hand-tuned point)."""
        spec = method(controller)
        out = {"sigma_scale": 1.0, "lam": float(self.sampler.lam)}
        if spec.robust:
            out["kappa"] = float(self.rule.kappa)
        for p in spec.tunable:
            out[p.name] = float(getattr(self.methods.options(spec), p.name.split(".")[1]))
        return out

    def with_values(self, controller: str, params: dict[str, float]) -> ControllerSettings:
        """These settings with tuned ``params`` (names of ``space(controller)``) applied."""
        allowed = {p.name: p for p in space(controller)}
        for k, v in params.items():
            if k not in allowed:
                raise fail("params", k, f"is not tuned for {controller}; allowed {list(allowed)}")
            if not allowed[k].contains(float(v)):
                raise fail(f"params.{k}", v, f"must lie in [{allowed[k].low:g}, "
                           f"{allowed[k].high:g}]")
        s = self.sampler
        sampler = dataclasses.replace(
            s, sigma=tuple(params.get("sigma_scale", 1.0) * v for v in s.sigma),
            lam=float(params.get("lam", s.lam)))
        rule = (dataclasses.replace(self.rule, kappa=float(params["kappa"]))
                if "kappa" in params else self.rule)
        methods, spec = self.methods, method(controller)
        for k, v in params.items():
            if "." in k:
                name = k.split(".")[1]
                sub = methods.options(spec)  # the method's own options
                value = round(v) if isinstance(getattr(sub, name), int) else float(v)
                methods = methods.with_options(spec, dataclasses.replace(sub, **{name: value}))
        return ControllerSettings(sampler, self.q_beta, rule, methods)


class TunedFileError(ValueError):
    """A tuned-values file, or one of its entries, that cannot be used; the message names the
    file and says how to make a good one."""


@dataclass(frozen=True)
class MapSeeds:
    """The maps of one family an entry was trained or validated on."""

    family: str
    seeds: tuple[int, ...]


@dataclass(frozen=True)
class Evaluation:
    """The hand-tuned point's and the tuned point's scores under the entry's objective on one
    set of episodes: ``episodes`` of them (per trial, for training) on ``maps``. All None: not
    evaluated (an entry tuned without validation); a score alone None: not finite."""

    maps: tuple[MapSeeds, ...] | None
    episodes: int | None
    hand: float | None
    tuned: float | None

    @property
    def done(self) -> bool:
        return self.maps is not None

    def seeds(self, family: str) -> tuple[int, ...]:
        return tuple(s for m in self.maps or () if m.family == family for s in m.seeds)

    def as_dict(self) -> dict:
        return {"maps": None if self.maps is None else
                [{"family": m.family, "seeds": list(m.seeds)} for m in self.maps],
                "episodes": self.episodes, "hand": self.hand, "tuned": self.tuned}


@dataclass(frozen=True)
class Tuned:
    """The shipped values of one (system, controller) pair and their provenance.

    ``hand`` is the hand-tuned point the search started from, ``tuned`` the search's result
    (its best point on the validation episodes; the hand point itself when no trial beat it on
    training). ``params`` are the values an evaluation uses: ``tuned`` when ``kept`` is
    "tuned", ``hand`` when ``kept`` is "hand" (the tuned point did not beat it on validation).
    ``training`` and ``validation`` hold both points' scores. ``disturbance`` is the label of
    the disturbance both were run under; ``system_hash`` the
    :func:`~workbench.scenarios.systems.definition_hash` of the system as the tuning run
    defined it (None: not recorded; such an entry is refused for use); ``source`` the file the
    entry was read from."""

    system: str
    controller: str
    kept: str
    params: dict[str, float]
    hand: dict[str, float]
    tuned: dict[str, float]
    budget: TuningBudget
    objective: str
    disturbance: str
    training: Evaluation
    validation: Evaluation
    system_hash: str | None
    source: Path | None = field(default=None, compare=False)

    @property
    def score(self) -> float:
        """The tuned point's training score (NaN when not finite)."""
        return math.nan if self.training.tuned is None else self.training.tuned

    @property
    def start_score(self) -> float:
        """The hand-tuned point's training score (NaN when not finite)."""
        return math.nan if self.training.hand is None else self.training.hand

    @property
    def file(self) -> Path:
        return Path(self.source or SHIPPED)

    def as_dict(self) -> dict:
        return {"system": self.system, "controller": self.controller, "kept": self.kept,
                "params": dict(self.params), "hand": dict(self.hand), "tuned": dict(self.tuned),
                "objective": self.objective, "disturbance": self.disturbance,
                "system_hash": self.system_hash, "budget": dataclasses.asdict(self.budget),
                "training": self.training.as_dict(), "validation": self.validation.as_dict()}

    @classmethod
    def from_dict(cls, d: object, source: Path | None = None) -> Tuned:
        """An entry as :meth:`as_dict` writes it; anything else is refused with a
        :class:`TunedFileError` naming ``source`` (default: the shipped file)."""
        return _entry(d, Path(source or SHIPPED), None)


ENTRY_KEYS = ("system", "controller", "kept", "params", "hand", "tuned", "objective",
              "disturbance", "system_hash", "budget", "training", "validation")
HASH = re.compile(r"[0-9a-f]{16}")  # definition_hash's form
EVALUATION_KEYS = ("maps", "episodes", "hand", "tuned")


def _bad(path: Path, where: str, problem: str) -> TunedFileError:
    return TunedFileError(f"{path}: {where}{problem}; {RERUN} to write it again")


def _keys(path: Path, where: str, d: object, keys: tuple[str, ...]) -> dict:
    if not isinstance(d, dict):
        raise _bad(path, where, f"expected an object with keys {list(keys)}, got {d!r}")
    missing = [k for k in keys if k not in d]
    extra = [k for k in d if k not in keys]
    if missing or extra:
        raise _bad(path, where, (f"missing {missing}" if missing else "")
                   + (", " if missing and extra else "") + (f"unknown {extra}" if extra else ""))
    return d


def _number(path: Path, where: str, v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, Real) or not math.isfinite(float(v)):
        raise _bad(path, where, f"expected a finite number, got {v!r}")
    return float(v)


def _score(path: Path, where: str, v: object) -> float | None:
    return None if v is None else _number(path, where, v)  # strict JSON: non-finite is null


def _count(path: Path, where: str, v: object) -> int:
    if isinstance(v, bool) or not isinstance(v, Integral) or v < 1:
        raise _bad(path, where, f"expected a positive integer, got {v!r}")
    return int(v)


def _params(path: Path, where: str, d: object) -> dict[str, float]:
    if not isinstance(d, dict) or not d:
        raise _bad(path, where, f"expected a non-empty object of parameter values, got {d!r} "
                   "(an empty one would silently be the hand-tuned point)")
    return {str(k): _number(path, f"{where}.{k}: ", v) for k, v in d.items()}


def _maps(path: Path, where: str, v: object) -> tuple[MapSeeds, ...]:
    if not isinstance(v, list) or not v:
        raise _bad(path, where, f"expected a non-empty list of {{family, seeds}}, got {v!r}")
    out = []
    for i, m in enumerate(v):
        m = _keys(path, f"{where}[{i}]: ", m, ("family", "seeds"))
        fam, seeds = m["family"], m["seeds"]
        if not isinstance(fam, str) or not fam:
            raise _bad(path, f"{where}[{i}].family: ", f"expected a family name, got {fam!r}")
        if (not isinstance(seeds, list) or not seeds
                or any(isinstance(s, bool) or not isinstance(s, Integral) or s < 0
                       for s in seeds)):
            raise _bad(path, f"{where}[{i}].seeds: ",
                       f"expected a non-empty list of map seeds, got {seeds!r}")
        out.append(MapSeeds(fam, tuple(int(s) for s in seeds)))
    return tuple(out)


def _evaluation(path: Path, where: str, d: object, optional: bool) -> Evaluation:
    d = _keys(path, where, d, EVALUATION_KEYS)
    if optional and all(d[k] is None for k in EVALUATION_KEYS):
        return Evaluation(None, None, None, None)
    return Evaluation(_maps(path, f"{where}maps", d["maps"]),
                      _count(path, f"{where}episodes: ", d["episodes"]),
                      _score(path, f"{where}hand: ", d["hand"]),
                      _score(path, f"{where}tuned: ", d["tuned"]))


def _entry(d: object, path: Path, index: int | None) -> Tuned:
    at = "" if index is None else f"entry {index}: "
    d = _keys(path, at, d, ENTRY_KEYS)
    for k in ("system", "controller", "objective", "disturbance"):
        if not isinstance(d[k], str) or not d[k]:
            raise _bad(path, f"{at}{k}: ", f"expected a non-empty string, got {d[k]!r}")
    at = f"entry {'' if index is None else str(index) + ' '}({d['system']}, {d['controller']}): "
    if d["kept"] not in KEPT:
        raise _bad(path, f"{at}kept: ", f"expected one of {KEPT}, got {d['kept']!r}")
    params = _params(path, f"{at}params", d["params"])
    hand = _params(path, f"{at}hand", d["hand"])
    tuned_ = _params(path, f"{at}tuned", d["tuned"])
    if params != (tuned_ if d["kept"] == "tuned" else hand):
        raise _bad(path, at, f"kept is {d['kept']!r} but params differ from {d['kept']!r}")
    b = d["budget"]
    try:
        budget = TuningBudget(**b) if isinstance(b, dict) else None
    except (TypeError, ValueError) as exc:
        raise _bad(path, f"{at}budget: ", str(exc)) from exc
    if budget is None:
        raise _bad(path, f"{at}budget: ", f"expected an object, got {b!r}")
    h = d["system_hash"]
    if h is not None and not (isinstance(h, str) and HASH.fullmatch(h)):
        raise _bad(path, f"{at}system_hash: ", f"expected null or 16 hex digits, got {h!r}")
    training = _evaluation(path, f"{at}training.", d["training"], False)
    validation = _evaluation(path, f"{at}validation.", d["validation"], True)
    return Tuned(d["system"], d["controller"], d["kept"], params, hand, tuned_, budget,
                 d["objective"], d["disturbance"], training, validation, h, path)


@cache
def _parse(path: Path, stamp: tuple[int, int]) -> dict[tuple[str, str], Tuned]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise _bad(path, "", f"cannot be read as JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise _bad(path, "", "is not a tuned-values file (expected an object with 'format' "
                   "and 'tuned')")
    if "format" not in data:
        raise _bad(path, "", f"is in an older format (no 'format' field); this version reads "
                   f"format {FORMAT}")
    if data["format"] != FORMAT:
        raise _bad(path, "", f"is in format {data['format']!r}; this version reads format "
                   f"{FORMAT}")
    _keys(path, "", data, ("format", "tuned"))
    if not isinstance(data["tuned"], list):
        raise _bad(path, "tuned: ", f"expected a list of entries, got {data['tuned']!r}")
    out: dict[tuple[str, str], Tuned] = {}
    for i, e in enumerate(data["tuned"]):
        t = _entry(e, path, i)
        if (t.system, t.controller) in out:
            raise _bad(path, f"entry {i}: ", f"repeats ({t.system}, {t.controller})")
        out[(t.system, t.controller)] = t
    return out


def _read(path: Path) -> dict[tuple[str, str], Tuned]:
    try:
        st = path.stat()
    except FileNotFoundError:
        return {}
    return _parse(path, (st.st_mtime_ns, st.st_size))  # a rewritten file is read again


def shipped(path: Path | None = None) -> dict[tuple[str, str], Tuned]:
    """The shipped tuned defaults by (system, controller) ({} when none are shipped). An older
    or damaged file raises :class:`TunedFileError` naming it."""
    return dict(_read(Path(path or SHIPPED)))


def tuned(system: str, controller: str, path: Path | None = None) -> Tuned | None:
    """The shipped tuned parameters of (``system``, ``controller``), or None."""
    return _read(Path(path or SHIPPED)).get((system, controller))


def write(entries: Iterable[Tuned], path: Path | None = None) -> Path:
    """Write ``entries`` (sorted by system and controller) as a tuned-values file of format
    :data:`FORMAT` (strict JSON: a non-finite score is null). Each entry is read back before
    the file is replaced, so a file this writes is one :func:`shipped` reads."""
    from workbench.study.io import atomic_write_text, dumps_json

    target = Path(path or SHIPPED)
    rows = [t.as_dict() for t in sorted(entries, key=lambda t: (t.system, t.controller))]
    text = dumps_json({"format": FORMAT, "tuned": rows}, indent=2) + "\n"
    seen = set()
    for i, r in enumerate(json.loads(text)["tuned"]):
        t = _entry(r, target, i)
        if (t.system, t.controller) in seen:
            raise _bad(target, f"entry {i}: ", f"repeats ({t.system}, {t.controller})")
        seen.add((t.system, t.controller))
    atomic_write_text(target, text)
    return target


def check_usable(entry: Tuned, families: Iterable[str], seeds: Iterable[int]) -> Tuned:
    """Refuse to evaluate ``entry`` on the test maps ``seeds`` of each of ``families``: an
    entry without a system hash or tuned on another definition of its system than the current
    one, one tuned without validation, one whose parameters are not its controller's full
    search space, or one whose training or validation maps of a family share a seed with the
    test maps. Returns the entry. Errors name the system, the controller and the file."""
    who = f"the tuned values of ({entry.system}, {entry.controller}) in {entry.file}"
    if entry.system_hash is None:
        raise TunedFileError(f"{who} have no system hash (null: the definition of "
                             f"{entry.system} they were tuned on was not recorded), so whether "
                             f"they were tuned on its current definition is unknown; {RERUN}")
    now = definition_hash(entry.system)
    if entry.system_hash != now:
        raise TunedFileError(f"{who} were tuned on {entry.system} with definition hash "
                             f"{entry.system_hash}, but its current definition hashes to {now}: "
                             f"the system's definition changed since tuning: {RERUN}")
    val = entry.validation
    if not val.done or val.hand is None or val.tuned is None:
        raise TunedFileError(f"{who} have no validation score (null: tuned without held-out "
                             f"validation maps, or not finite), so how well they generalise "
                             f"is unknown; {RERUN}")
    names = {p.name: p for p in space(entry.controller)}
    if set(entry.params) != set(names):
        raise TunedFileError(f"{who} set {sorted(entry.params)}; the controller's search space "
                             f"is {sorted(names)}; {RERUN}")
    for k, v in entry.params.items():
        if not names[k].contains(v):
            raise TunedFileError(f"{who} set {k} = {v:g}, outside its search range "
                                 f"[{names[k].low:g}, {names[k].high:g}]; {RERUN}")
    test = set(seeds)
    for fam in dict.fromkeys(families):
        for what, ev in (("training", entry.training), ("validation", entry.validation)):
            common = sorted(test & set(ev.seeds(fam)))
            if common:
                raise TunedFileError(
                    f"{who} were tuned with {fam} maps {common} among their {what} maps, and "
                    f"this evaluation tests on them (test seeds {min(test)}..{max(test)}): "
                    f"choose test seeds disjoint from seeds {sorted(ev.seeds(fam))} of {fam}, "
                    f"or {RERUN} on other maps")
    return entry


@dataclass(frozen=True)
class TunedScores:
    """One shipped entry's scores under its objective, for a report: training (per trial:
    ``training_episodes`` episodes) and validation (``validation_episodes``; None when not
    validated) of the hand-tuned point and the tuned one; ``kept`` says which one the
    shipped ``params`` are (a test of the shipped values with ``kept`` "hand" tests the
    hand-tuned point)."""

    system: str
    controller: str
    kept: str
    training_hand: float
    training_tuned: float
    training_episodes: int
    validation_hand: float | None
    validation_tuned: float | None
    validation_episodes: int | None


def scores(path: Path | None = None) -> list[TunedScores]:
    """The training and validation scores of every shipped entry, sorted by system and
    controller."""
    out = []
    for (s, c), t in sorted(shipped(path).items()):
        out.append(TunedScores(s, c, t.kept, t.start_score, t.score,
                               int(t.training.episodes or 0), t.validation.hand,
                               t.validation.tuned, t.validation.episodes))
    return out
