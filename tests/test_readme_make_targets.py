"""The README's make targets, in the README's order: after `make study`, every documented
`make TARGET VAR=VALUE ...` exists in the Makefile and works after the ones before it. Checked
without running a study (`make -n` prints each command): each run goes to a folder that holds
only runs of the same study, profile and overrides (a folder holds one config's run, so two
configs in one folder would be refused), every profile a target passes is one of its study's,
and every documented config resolves."""

from __future__ import annotations

import itertools
import re
import shlex
import subprocess
from pathlib import Path

import pytest

from workbench.study.runner import resolve_config
from workbench.study.spec import registry

ROOT = Path(__file__).parents[1]
README = (ROOT / "README.md").read_text()
REGISTRY = registry()
# a placeholder in the README's variables -> a value for the check
PLACEHOLDERS = {"N": "2", "DIR": "/tmp/workbench-out"}


def _expand(words: list[str]) -> list[list[str]]:
    """``PROFILE=paper|full`` -> one argument list per alternative."""
    out: list[list[str]] = [[]]
    for w in words:
        name, sep, value = w.partition("=")
        options = [f"{name}={PLACEHOLDERS.get(v, v)}" for v in value.split("|")] if sep else [w]
        out = [[*o, opt] for o in out for opt in options]
    return out


def documented() -> list[list[str]]:
    """Every make invocation of the README, in its order (inline code and command blocks),
    each as make's arguments."""
    found = []
    for m in re.finditer(r"`make ([^`]+)`|^make ([a-z][\w-]*)", README, re.M):
        text = m.group(1) or m.group(2)
        found += _expand(shlex.split(text))
    return found


def documented_profiles() -> set[str]:
    """Every PROFILE value the README names for the make targets."""
    return {p for m in re.finditer(r"`PROFILE=([\w|]+)`", README) for p in m.group(1).split("|")}


def runs(args: list[str]) -> list[tuple[str, str, tuple[str, ...], str]]:
    """``make -n ARGS``'s study runs: (study, profile, --set overrides, --out folder)."""
    r = subprocess.run(["make", "-n", *args], capture_output=True, text=True, cwd=ROOT,
                       timeout=60)
    assert r.returncode == 0, f"make {' '.join(args)}: {r.stderr}"
    found = []
    for line in r.stdout.replace("\\\n", " ").splitlines():
        words = shlex.split(line)
        if len(words) < 3 or not words[0].endswith("workbench") or words[1] != "run":
            continue
        study, profile, sets, out = words[2], None, [], None
        for flag, value in itertools.pairwise(words[3:]):
            if flag == "--profile":
                profile = value
            elif flag == "--set":
                sets.append(value)
            elif flag == "--out":
                out = value
        assert profile and out, f"make {' '.join(args)}: {line} has no --profile or --out"
        found.append((study, profile, tuple(sets), out))
    return found


def test_the_readme_documents_the_targets_people_run():
    targets = {a[0] for a in documented()}
    assert {"study", "test", "reports", "study-tracking", "study-arena", "tune-arena",
            "docs", "bench"} <= targets
    assert documented()[0] == ["study"]


def test_the_readme_targets_run_one_after_another():
    """`make study`, then each documented invocation in the README's order, then each study
    target with every documented PROFILE and with an override: no folder gets two configs."""
    readme = [["study"], *documented()]
    study_targets = sorted({a[0] for a in readme if a[0].startswith(("study-", "tune-"))})
    more = [[t, f"PROFILE={p}"] for t in study_targets for p in sorted(documented_profiles())]
    more += [[t, "PROFILE=paper", "SET=seed=7"] for t in study_targets]
    owner: dict[str, tuple] = {}
    checked: set[tuple] = set()
    for args in readme + more:
        for study, profile, sets, out in runs(args):
            spec = REGISTRY[study]
            if profile not in spec.profiles:  # refused with a message before anything is written
                assert args not in readme, f"make {' '.join(args)}: {study} has no {profile}"
                continue
            first = owner.setdefault(out, (study, profile, sets, args))
            assert first[:3] == (study, profile, sets), (
                f"make {' '.join(args)} runs {study} --profile {profile} {sets} into {out}, "
                f"which already holds the run of make {' '.join(first[3])}")
            if (study, profile, sets) not in checked:
                checked.add((study, profile, sets))
                resolve_config(spec, profile, None, list(sets))  # the config is valid


@pytest.mark.parametrize("args", [["study-tracking", "OUT=/tmp/x y"],
                                  ["study-arena", "PROFILE=verdict", "OUT=/tmp/v"]])
def test_out_chooses_the_folder(args):
    assert [r[3] for r in runs(args)] == [args[-1].removeprefix("OUT=")]


def test_a_set_with_quotes_gets_a_folder_of_its_own():
    one = runs(["study-tracking", "SET=methods=['bas'] n_seeds=4"])
    two = runs(["study-tracking", "SET=methods=['ecbf'] n_seeds=4"])
    assert one[0][3] != two[0][3] and one[0][3].startswith("reports/tracking_comparison_quick_set-")
    assert runs(["study-tracking", "SET=methods=['bas'] n_seeds=4"]) == one  # stable


@pytest.mark.parametrize("quick_run", [True, False])
def test_make_reports_links_each_profiles_run_from_its_study(tmp_path, quick_run):
    from workbench.study.report_site import build_site

    folders = ["tracking_comparison_full", *(["tracking_comparison"] if quick_run else [])]
    for name in folders:
        (tmp_path / name).mkdir()
        (tmp_path / name / "manifest.json").write_text('{"study": "tracking_comparison"}')
        (tmp_path / name / "report.md").write_text(f"# {name}\n")
    index = (build_site(tmp_path, REGISTRY)).read_text()
    section = index.split('<section id="tracking">', 1)[1].split("</section>", 1)[0]
    assert 'href="tracking_comparison_full/report.html">full</a>' in section
    assert 'id="other-runs"' not in index  # listed with its study, not as another run
    assert (tmp_path / "tracking_comparison_full" / "report.html").is_file()
