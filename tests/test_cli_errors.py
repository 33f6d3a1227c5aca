"""Failures a user causes end with a message naming the problem, not a traceback: exit 2 for an
input that is not allowed (a config value, an argument, a study's registration, the compiler, a
tuned pair that is not shipped, a --set nested too deeply), exit 1 with the list of tasks for a
run whose tasks raised or timed out (recorded in errors.json, retried by a rerun)."""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import pytest

from workbench.cli import main
from workbench.study.config_io import MAX_NESTING

ROOT = Path(__file__).parents[1]
WORKBENCH = str(Path(sys.executable).parent / "workbench")

FILES = {
    "__init__.py": '''
        from pathlib import Path

        from errtoy_study.config import ToyConfig
        from workbench.study.spec import StudySpec

        STUDY = StudySpec(
            name="errtoy", description="draws", config_type=ToyConfig,
            directory=Path(__file__).parent, tasks="errtoy_study.tasks:declare",
            summarise="errtoy_study.tasks:summary", report="errtoy_study.tasks:report",
            prepare="errtoy_study.tasks:prepare")
        ''',
    "config.py": '''
        from dataclasses import dataclass

        from workbench.validation import integer, real


        @dataclass(frozen=True)
        class ToyConfig:
            n: int = 2
            sleep: float = 0.0
            compile: str = "no"
            label: str = "toy"
            seed: int = 0

            def __post_init__(self):
                integer("n", self.n, 1)
                real("sleep", self.sleep, 0.0)
        ''',
    "tasks.py": '''
        import time
        from dataclasses import dataclass

        import numpy as np

        from workbench.study import TaskOutput
        from workbench.study.io import atomic_write_text
        from workbench.study.spec import Declaration, Summary
        from workbench.validation import fail


        @dataclass(frozen=True)
        class Draw:
            i: int


        def build():
            import casadi as ca

            from workbench.codegen.cache import build_library

            x = ca.SX.sym("x")
            build_library("errtoy", [ca.Function("errtoy_f", [x], [2 * x])], rebuild=True)


        def prepare(config, out):
            if config.compile == "prepare":
                build()


        def run(task, ctx, config, prepared):
            if config.compile == "task":
                build()
            time.sleep(config.sleep)
            return TaskOutput(tables={"draws": {"value": np.array([ctx.rng().standard_normal()])}})


        def declare(config):
            if config.label == "refused":
                raise fail("label", config.label, "a study's own check, made when declaring")
            tasks = tuple(Draw(i) for i in range(config.n))
            return Declaration(tasks, run, {}, plan=tasks)


        def summary(finished):
            return Summary({"n": len(finished.ids)})


        def count(config):
            return config.n  # not a Declaration


        def report(finished, summary):
            path = finished.out / "report.md"
            atomic_write_text(path, f"# Toy\\n\\nLabel: {finished.config.label}\\n")
            return path
        ''',
    "quick.toml": "n = 2\n",
}


def package(root: Path, **changes: str) -> str:
    """The toy study package under ``root`` (a new module name each time, so that tests in one
    process do not share it), with ``changes`` (file name -> text) applied; its name."""
    name = f"errtoy_{uuid.uuid4().hex[:10]}"
    pkg = root / name
    pkg.mkdir()
    for file, text in {**FILES, **changes}.items():
        (pkg / file).write_text(textwrap.dedent(text).lstrip().replace("errtoy_study", name))
    return name


@pytest.fixture
def cli(tmp_path, monkeypatch, capsys):
    """``cli(*argv, studies=..., **env)`` -> (exit code, stderr) of ``workbench.cli.main``,
    with the toy packages under tmp_path importable."""
    monkeypatch.syspath_prepend(str(tmp_path))

    def call(*argv: str, studies: str, **env: str) -> tuple[int, str]:
        monkeypatch.setenv("WORKBENCH_STUDIES", studies)
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        capsys.readouterr()
        rc = main(list(argv))
        return rc, capsys.readouterr().err

    return call


def refused(result: tuple[int, str], code: int, *words: str) -> None:
    """Exit ``code``, no traceback, and an error message holding each of ``words``."""
    rc, err = result
    assert "Traceback" not in err, err
    assert rc == code, (rc, err)
    assert re.search(r"^workbench [a-z-]+: error: ", err, re.M), err
    for w in words:
        assert w in err, (w, err)


# ------------------------------------------------------------------------------ time limits
def test_a_task_over_the_time_limit_is_a_recorded_error_with_a_message(tmp_path):
    """End to end through the installed command."""
    name = package(tmp_path)
    out = tmp_path / "out"
    env = {**os.environ, "WORKBENCH_STUDIES": name,
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([WORKBENCH, "run", "errtoy", "--workers", "0", "--out", str(out),
                        "--task-timeout", "0.2", "--set", "sleep=0.6"], capture_output=True,
                       text=True, env=env, timeout=300, cwd=ROOT)
    refused((r.returncode, r.stderr), 1, "2 of 2 tasks raised",
            "TimeoutError: task timed out after 0.2 s", str(out / "errors.json"),
            "a rerun retries them")
    assert len(json.loads((out / "errors.json").read_text())) == 2


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_a_time_limit_that_is_not_a_positive_number_is_refused(tmp_path, cli, value):
    name = package(tmp_path)
    for extra in (("--dry-run",), ("--workers", "0")):  # checked even when nothing would run
        refused(cli("run", "errtoy", "--out", str(tmp_path / "out"), f"--task-timeout={value}",
                    *extra, studies=name), 2, "--task-timeout", "task_timeout_s")
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- compile limits
def _slow_compiler(tmp_path: Path) -> dict[str, str]:
    cc = tmp_path / "slowcc"
    cc.write_text('#!/bin/sh\nif [ "$1" = "--version" ]; then echo "slowcc 1.0"; exit 0; fi\n'
                  "exec sleep 30\n")
    cc.chmod(cc.stat().st_mode | stat.S_IXUSR)
    return {"WORKBENCH_CC": str(cc), "WORKBENCH_COMPILE_TIMEOUT": "0.5",
            "WORKBENCH_CACHE_DIR": str(tmp_path / "cache")}


def test_a_compile_over_the_time_limit_names_the_variable_and_its_value(tmp_path, cli):
    name = package(tmp_path)
    refused(cli("run", "errtoy", "--workers", "0", "--set", "compile=prepare", "--out",
                str(tmp_path / "out"), studies=name, **_slow_compiler(tmp_path)), 2,
            "WORKBENCH_COMPILE_TIMEOUT", "timed out after 0.5 s")


def test_a_compile_timeout_in_a_task_is_a_recorded_error_naming_the_variable(tmp_path, cli):
    name = package(tmp_path)
    refused(cli("run", "errtoy", "--workers", "0", "--set", "compile=task", "--out",
                str(tmp_path / "out"), studies=name, **_slow_compiler(tmp_path)), 1,
            "2 of 2 tasks raised", "CompileError", "timed out after 0.5 s",
            "WORKBENCH_COMPILE_TIMEOUT")


# ----------------------------------------------------------------------------- registrations
BAD_REGISTRATIONS = [
    ("no module", {}, "{name}_nope", ["_nope'", "does not exist"]),
    ("no STUDY", {"__init__.py": "X = 1\n"}, "{name}", ["defines no STUDY"]),
    ("STUDY not a spec", {"__init__.py": "STUDY = 'errtoy'\n"}, "{name}",
     ["STUDY = str", "StudySpec"]),
    ("spec refused", {"__init__.py": FILES["__init__.py"].replace('name="errtoy"',
                                                                   'name="err toy"')},
     "{name}", ["StudySpec.name", "'err toy'"]),
    ("typo in the module", {"__init__.py": "import os\n\nSTUDY = undefined_name\n"},
     "{name}", ["NameError", "undefined_name", "__init__.py:3"]),
    ("syntax error", {"__init__.py": "STUDY = (\n"}, "{name}",
     ["SyntaxError", "__init__.py:1"]),
    ("registered twice", {}, "{name},{name}", ["two studies are named 'errtoy'"]),
]


@pytest.mark.parametrize("case, files, studies, words", BAD_REGISTRATIONS,
                         ids=[c[0] for c in BAD_REGISTRATIONS])
def test_a_malformed_registration_names_the_study_and_what_is_wrong(tmp_path, cli, case, files,
                                                                     studies, words):
    name = package(tmp_path, **files)
    for argv in (("list",), ("run", "errtoy", "--dry-run"), ("report", "errtoy")):
        refused(cli(*argv, studies=studies.format(name=name)), 2, name, *words)


BAD_ENTRY_POINTS = [
    ("no such module", 'tasks="errtoy_study.tasks:declare"', 'tasks="errtoy_study.nope:declare"',
     ["study 'errtoy'", ".nope:declare'", "does not exist"]),
    ("no such function", 'tasks="errtoy_study.tasks:declare"', 'tasks="errtoy_study.tasks:nope"',
     ["study 'errtoy'", ".tasks.nope does not exist"]),
    ("not a function", 'tasks="errtoy_study.tasks:declare"', 'tasks="errtoy_study.tasks:np"',
     ["study 'errtoy'", ".tasks.np is not a function"]),
    ("returns no declaration", 'tasks="errtoy_study.tasks:declare"',
     'tasks="errtoy_study.tasks:count"', ["study 'errtoy'", "tasks returned int"]),
    ("broken report module", 'report="errtoy_study.tasks:report"',
     'report="errtoy_study.config:missing"', ["study 'errtoy'", ".config.missing does not exist"]),
]


@pytest.mark.parametrize("case, old, new, words", BAD_ENTRY_POINTS,
                         ids=[c[0] for c in BAD_ENTRY_POINTS])
def test_a_bad_entry_point_names_the_study_and_the_entry(tmp_path, cli, case, old, new, words):
    name = package(tmp_path, **{"__init__.py": FILES["__init__.py"].replace(old, new)})
    argv = ("run", "errtoy", "--workers", "0", "--out", str(tmp_path / "out"))
    refused(cli(*argv, studies=name), 2, *words)


def test_a_value_the_studys_own_declaration_refuses_is_a_message(tmp_path, cli):
    name = package(tmp_path)
    for extra in (("--dry-run",), ("--workers", "0", "--out", str(tmp_path / "out"))):
        refused(cli("run", "errtoy", "--set", "label=refused", *extra, studies=name), 2,
                "study 'errtoy'", "label = 'refused' is invalid")


def test_a_missing_tuned_pair_at_dry_run_names_the_pair_and_how_to_make_it(cli):
    refused(cli("run", "arena", "--dry-run", "--set", 'systems=["planar_quadrotor"]', "--set",
                'controllers=["sa_rmppi"]', studies=""), 2,
            "(planar_quadrotor, sa_rmppi)", "make tune-arena")


# ------------------------------------------------------------------------------- nesting
def _deep(n: int) -> str:
    return "[" * n + "]" * n


@pytest.mark.parametrize("item", [
    ".".join(["a"] * (MAX_NESTING + 1)) + "=1",         # a deep key
    "n=" + _deep(MAX_NESTING + 1),                        # a deep value
    "n=" + _deep(5000),                                   # deeper than the TOML reader goes
    "n=" + "{a=" * 3000 + "1" + "}" * 3000,               # inline tables
    ".".join(["a"] * 30) + ".b=" + _deep(5),              # key and value together
])
def test_a_set_nested_too_deeply_names_the_limit(tmp_path, cli, item):
    name = package(tmp_path)
    for command in (("run", "errtoy", "--dry-run"), ("show-config", "errtoy")):
        refused(cli(*command, "--set", item, studies=name), 2, "--set",
                f"at most {MAX_NESTING} levels")


def test_a_config_file_nested_too_deeply_names_the_limit(tmp_path, cli):
    name = package(tmp_path)
    for depth in (MAX_NESTING + 1, 900):
        deep = tmp_path / f"deep{depth}.toml"
        deep.write_text(f"n = {_deep(depth)}\n")
        refused(cli("run", "errtoy", "--dry-run", "--config", str(deep), studies=name), 2,
                str(deep), f"at most {MAX_NESTING} levels")


def test_nesting_up_to_the_limit_is_read_as_before(tmp_path, cli):
    name = package(tmp_path)
    rc, err = cli("run", "errtoy", "--dry-run", "--set", "n=" + _deep(MAX_NESTING), studies=name)
    refused((rc, err), 2, "n = ")  # read, then refused by the type check: not an integer
    assert "levels" not in err
