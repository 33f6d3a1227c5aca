"""workbench.study.config_io: TOML configs into frozen dataclasses, generic over field types."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from typing import Literal

import pytest

from studies.navigation.config import StudyConfig as NavigationConfig
from studies.tracking_comparison.config import StudyConfig
from workbench.study.config_io import ConfigError, dump, keys, load, merge, parse_sets, to_dict


@dataclass(frozen=True)
class Inner:
    rate: float = 1.0
    mode: Literal["a", "b"] = "a"

    def __post_init__(self):
        if self.rate <= 0:
            raise ValueError(f"rate = {self.rate} is invalid: must be > 0")


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    count: int = 3
    flag: bool = False
    values: tuple[float, ...] = (1.0, 2.0)
    pair: tuple[int, str] = (1, "one")
    maybe: float | None = None
    inner: Inner = field(default_factory=Inner)


def test_defaults_values_and_nested_tables():
    assert load(Outer, {}) == Outer()
    cfg = load(Outer, {"count": 5, "values": [1, 2.5], "inner": {"rate": 2, "mode": "b"},
                       "pair": [2, "two"], "maybe": 4})
    assert cfg == Outer(count=5, values=(1.0, 2.5), pair=(2, "two"), maybe=4.0,
                        inner=Inner(2.0, "b"))
    assert isinstance(cfg.values[0], float) and isinstance(cfg.inner.rate, float)
    assert keys(Outer) == ["name", "count", "flag", "values", "pair", "maybe", "inner.rate",
                           "inner.mode"]


@pytest.mark.parametrize("data, match", [
    ({"count": 1.5}, r"^count = 1.5 is invalid: expected an integer"),
    ({"count": True}, r"^count = True is invalid: expected an integer"),
    ({"flag": 1}, r"^flag = 1 is invalid: expected true or false"),
    ({"values": 3.0}, r"^values = 3.0 is invalid: expected a list of a number"),
    ({"values": [1, "2"]}, r"^values\[1\] = '2' is invalid: expected a number"),
    ({"pair": [1]}, r"^pair = \[1\] is invalid: expected a list of 2 items"),
    ({"inner": {"mode": "c"}}, r"^inner.mode = 'c' is invalid: expected one of 'a', 'b'"),
    ({"inner": 3}, r"^inner = 3 is invalid: expected a table \(Inner\)"),
    ({"inner": {"rate": -1}}, r"^inner: rate = -1.0 is invalid: must be > 0"),
    ({"cuont": 2}, r"^unknown key 'cuont'; did you mean 'count'\?"),
    ({"inner": {"rat": 2}}, r"^unknown key 'inner.rat'; did you mean 'inner.rate'\?"),
    ({"zzz": 2}, r"^unknown key 'zzz' \(valid keys: name, count"),
])
def test_errors_name_the_key_the_value_and_what_is_allowed(data, match):
    with pytest.raises(ConfigError, match=match):
        load(Outer, data)


def test_set_overrides_parse_toml_literals_and_dotted_keys():
    sets = parse_sets(["count=7", "inner.rate=1e-3", "values=[1, 2, 3]", "name=plain word",
                       'inner.mode="b"', "flag=true"])
    assert sets == {"count": 7, "inner": {"rate": 1e-3, "mode": "b"}, "values": [1, 2, 3],
                    "name": "plain word", "flag": True}
    assert load(Outer, merge({"count": 1, "inner": {"mode": "a"}}, sets)).inner.mode == "b"
    assert parse_sets(["r=2"], aliases={"r": "inner.rate"}) == {"inner": {"rate": 2}}
    with pytest.raises(ConfigError, match="expected key=value"):
        parse_sets(["count"])


@dataclass(frozen=True)
class WithDerived:
    low: float = 0.0
    high: float = field(init=False)
    limit: float = float("inf")

    def __post_init__(self):
        object.__setattr__(self, "high", self.low + 1)


def test_derived_fields_are_not_written_and_inf_round_trips():
    cfg = WithDerived(2.0)
    assert to_dict(cfg) == {"low": 2.0, "limit": float("inf")}
    assert load(WithDerived, tomllib.loads(dump(cfg))) == cfg
    with pytest.raises(ConfigError, match="unknown key 'high'"):
        load(WithDerived, {"high": 1.0})


def test_merge_is_recursive_and_later_layers_win():
    assert merge({"a": 1, "t": {"x": 1, "y": 2}}, {"t": {"y": 3}}, {"a": 2}) == \
        {"a": 2, "t": {"x": 1, "y": 3}}


@pytest.mark.parametrize("cfg", [Outer(), Outer(count=9, maybe=2.0, inner=Inner(0.5, "b")),
                                 StudyConfig(n_rollouts=100, n_seeds=2),
                                 StudyConfig(methods=("bas",)), NavigationConfig()])
def test_dump_round_trips(cfg):
    text = dump(cfg, header="a header\nover two lines")
    assert text.startswith("# a header\n# over two lines\n")
    assert load(type(cfg), tomllib.loads(text)) == cfg
    assert "maybe" not in to_dict(Outer())  # None is left out (TOML has no null)


def test_tracking_config_aliases_and_suggestions():
    aliases = {"noise_std": "base.noise_std"}
    with pytest.raises(ConfigError, match=r"noise_std = -1\.? is invalid"):
        load(StudyConfig, parse_sets(["noise_std=-1"], aliases), aliases=aliases)
    with pytest.raises(ConfigError, match=r"did you mean 'noise_std' \(base.noise_std\)\?"):
        load(StudyConfig, parse_sets(["noise_sdt=1"], aliases), aliases=aliases)
