"""The WORKBENCH_* environment variables: switches take a documented set of words, and every
bad value stops the command line with status 2 and a message naming the variable and value."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from workbench.codegen.toolchain import find_toolchain

ROOT = Path(__file__).parents[1]
ON = ["1", "true", "TRUE", "yes", "Yes", "on", " ON "]
OFF = ["0", "false", "False", "no", "NO", "off", " Off "]


def _has_compiler(monkeypatch) -> bool:
    monkeypatch.delenv("WORKBENCH_NO_CODEGEN", raising=False)
    return find_toolchain() is not None


@pytest.mark.parametrize("value", OFF)
def test_no_codegen_off_keeps_code_generation_on(monkeypatch, value):
    if not _has_compiler(monkeypatch):
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", value)
    assert find_toolchain() is not None


@pytest.mark.parametrize("value", ON)
def test_no_codegen_on_switches_code_generation_off(monkeypatch, value):
    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", value)
    assert find_toolchain() is None


@pytest.mark.parametrize("value", OFF)
def test_vector_math_takes_the_same_words(monkeypatch, value):
    from workbench.sampling.kernels.vector_math import enabled

    monkeypatch.setenv("WORKBENCH_VECTOR_MATH", value)
    assert enabled() is False
    monkeypatch.setenv("WORKBENCH_VECTOR_MATH", ON[OFF.index(value)])
    assert enabled() is True


def test_a_bad_switch_names_the_variable_value_and_words(monkeypatch):
    from workbench.environment import EnvironmentVariableError

    monkeypatch.setenv("WORKBENCH_NO_CODEGEN", "maybe")
    with pytest.raises(EnvironmentVariableError,
                       match=r"^WORKBENCH_NO_CODEGEN = 'maybe' is invalid: allowed values are "
                             r"1, true, yes, on \(on\) and 0, false, no, off \(off\)"):
        find_toolchain()


def _read(name: str):
    """Read ``name`` where the workbench reads it."""
    if name == "WORKBENCH_VECTOR_MATH":
        from workbench.sampling.kernels.vector_math import enabled

        return enabled()
    if name == "WORKBENCH_VECTOR_BITS":
        from workbench.sampling.kernels.flags import lane_count

        return lane_count("float64")
    if name == "WORKBENCH_STUDIES":
        from workbench.study.spec import registry

        return registry()
    if name == "WORKBENCH_PLUGINS":
        from workbench.scenarios.plugins import load_plugins

        return load_plugins()
    if name == "WORKBENCH_CACHE_DIR":
        from workbench.codegen import cache_dir

        return cache_dir()
    if name == "WORKBENCH_COMPILE_TIMEOUT":
        from workbench.codegen.toolchain import compile_timeout

        return compile_timeout()
    return find_toolchain()


# variable, bad value, what the message must say after "<variable> = '<value>' is invalid: "
BAD = [
    ("WORKBENCH_NO_CODEGEN", "maybe", "allowed values are 1, true, yes, on"),
    ("WORKBENCH_NO_CODEGEN", "2", "allowed values are 1, true, yes, on"),
    ("WORKBENCH_VECTOR_MATH", "2", "allowed values are 1, true, yes, on"),
    ("WORKBENCH_VECTOR_BITS", "384", "allowed values are 256, 512"),
    ("WORKBENCH_COMPILE_TIMEOUT", "soon", "must be a finite number of seconds > 0"),
    ("WORKBENCH_COMPILE_TIMEOUT", "-5", "must be a finite number of seconds > 0"),
    ("WORKBENCH_CFLAGS", "-O2 '-march", "cannot be split into words"),
    ("WORKBENCH_CFLAGS", "-O2 -ffast-math", "-ffast-math changes floating-point semantics"),
    ("WORKBENCH_CC", "gcc -O2", "must be one program name or path"),
    ("WORKBENCH_STUDIES", "my studies", "'my studies' is not a module name"),
    ("WORKBENCH_PLUGINS", "ok_name, bad-name", "'bad-name' is not a module name"),
]


@pytest.mark.parametrize(("name", "value", "says"), BAD, ids=[f"{n}={v}" for n, v, _ in BAD])
def test_a_bad_value_is_an_error_naming_the_variable_and_value(monkeypatch, name, value, says):
    monkeypatch.setenv(name, value)
    with pytest.raises(ValueError) as info:
        _read(name)
    assert str(info.value).startswith(f"{name} = {value!r} is invalid: {says}")


def test_a_cache_dir_that_is_a_file_is_an_error(monkeypatch, tmp_path):
    a_file = tmp_path / "not_a_dir"
    a_file.write_text("")
    monkeypatch.setenv("WORKBENCH_CACHE_DIR", str(a_file))
    with pytest.raises(ValueError, match=rf"^WORKBENCH_CACHE_DIR = '{a_file}' is invalid: .*is "
                                         r"an existing file, not a directory"):
        _read("WORKBENCH_CACHE_DIR")


@pytest.mark.parametrize(("name", "value", "says"), [BAD[0], BAD[7]], ids=["switch", "flag"])
def test_the_command_line_exits_with_status_2_and_the_message(name, value, says):
    env = {k: v for k, v in os.environ.items() if not k.startswith("WORKBENCH_")}
    out = subprocess.run([sys.executable, "-m", "workbench.cli", "list"], capture_output=True,
                         text=True, cwd=ROOT, timeout=300, env={**env, name: value})
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert f"workbench list: error: {name} = {value!r} is invalid: {says}" in out.stderr
