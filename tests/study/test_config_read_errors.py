"""A config path that is not a small UTF-8 TOML file is a ConfigError naming the path and the
problem, never a traceback and never a hang: folders, binary and non-UTF-8 files, FIFOs and
devices (refused from stat, before opening), files above the size limit, deep nesting."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from workbench.cli import main
from workbench.study import config_io
from workbench.study.config_io import MAX_CONFIG_BYTES, ConfigError, read_toml


def _message(path) -> str:
    with pytest.raises(ConfigError) as exc:
        read_toml(path)
    return str(exc.value)


def test_a_folder_is_named_as_a_folder(tmp_path):
    msg = _message(tmp_path)
    assert msg == (f"config file {tmp_path} is a folder, not a file; give the path of a TOML "
                   "file")


@pytest.mark.parametrize(("data", "byte", "offset"), [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", 0x89, 0),  # a PNG image
    (b'label = "caf\xe9"\n', 0xE9, 12),  # Latin-1 text
    (b"seed = 1\n\xff\xfe", 0xFF, 9),
])
def test_a_file_that_is_not_utf8_names_the_first_bad_byte(tmp_path, data, byte, offset):
    path = tmp_path / "c.toml"
    path.write_bytes(data)
    assert _message(path) == (f"config file {path} is not UTF-8 text (byte 0x{byte:02x} at "
                              f"offset {offset}); save it as UTF-8 TOML")


def test_a_binary_file_that_happens_to_be_utf8_is_named_by_its_nul_byte(tmp_path):
    path = tmp_path / "c.toml"
    path.write_bytes(b"\x7fELF\x02\x01\x01\x00\x00seed = 1")
    assert _message(path) == (f"config file {path} is not text: it holds a NUL byte at offset 7 "
                              "(a binary file?); give a TOML file")


def test_a_fifo_is_refused_at_once_without_opening_it(tmp_path):
    """Before: open() of a FIFO without a writer blocks for ever. Run in a thread so that a
    regression fails here instead of hanging the suite (the writer end releases it)."""
    fifo = tmp_path / "config.toml"
    os.mkfifo(fifo)
    out: dict = {}

    def read():
        try:
            out["value"] = read_toml(fifo)
        except Exception as exc:  # handed to the test thread
            out["error"] = exc

    worker = threading.Thread(target=read, daemon=True)
    worker.start()
    worker.join(10.0)
    hung = worker.is_alive()
    if hung:  # release the blocked open(): a writer appears and leaves
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        worker.join(5.0)
    assert not hung, "read_toml blocked on a FIFO"
    assert isinstance(out.get("error"), ConfigError), out
    assert str(out["error"]) == (f"config file {fifo} is not a regular file: it is a named pipe "
                                 "(FIFO); give a TOML file (write a generated config to a file "
                                 "first)")


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero")
def test_an_endless_device_is_refused_without_reading():
    msg = _message("/dev/zero")
    assert msg.startswith("config file /dev/zero is not a regular file: it is a character "
                          "device")


def test_an_enormous_file_is_refused_from_its_size(tmp_path):
    path = tmp_path / "huge.toml"
    with open(path, "wb") as f:  # sparse: no disk space, 4 GiB by its size
        f.truncate(4 << 30)
    assert _message(path) == (f"config file {path} is larger than 1 MB ({4 << 30} bytes); a "
                              "config file is a small TOML file")


def test_the_read_is_capped_even_when_stat_was_fooled(tmp_path, monkeypatch):
    """A file that grows between stat and read: at most MAX_CONFIG_BYTES + 1 bytes are read."""
    path = tmp_path / "c.toml"
    path.write_bytes(b"#" * 100)
    monkeypatch.setattr(config_io, "MAX_CONFIG_BYTES", 10)
    assert "is larger than 10 bytes (100 bytes)" in _message(path)
    monkeypatch.setattr(config_io, "_check_kind", lambda path, st, limit: None)  # stat fooled
    assert "(it grew while being read)" in _message(path)
    assert MAX_CONFIG_BYTES == 1 << 20


def test_deep_nesting_is_a_toml_error_not_a_recursion_error(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("a = " + "[" * 100_000)
    assert _message(path) == (f"{path}: not valid TOML (arrays or inline tables nest too "
                              "deeply: a config nests at most 32 levels)")


def test_a_parent_that_is_a_file_is_named(tmp_path):
    (tmp_path / "f").write_text("x = 1")
    assert _message(tmp_path / "f" / "c.toml") == (
        f"config file {tmp_path / 'f' / 'c.toml'} does not exist (a parent of it is a file, "
        "not a folder)")


def test_an_unreadable_file_is_named(tmp_path):
    path = tmp_path / "locked.toml"
    path.write_text("x = 1")
    path.chmod(0)
    try:
        if os.access(path, os.R_OK):  # root reads anything
            pytest.skip("running as root")
        assert _message(path) == (f"config file {path} cannot be read (Permission denied)")
    finally:
        path.chmod(0o600)


def test_a_byte_order_mark_is_skipped_and_plain_files_still_read(tmp_path):
    path = tmp_path / "c.toml"
    path.write_bytes(b"\xef\xbb\xbfseed = 3\n")
    assert read_toml(path) == {"seed": 3}
    path.write_text('label = "café"\n[base]\nnoise_std = 5\n', encoding="utf-8")
    assert read_toml(path) == {"label": "café", "base": {"noise_std": 5}}


def test_the_command_line_reports_a_folder_config_in_one_line(tmp_path, capsys):
    assert main(["show-config", "tracking-demo", "--config", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"config file {tmp_path} is a folder, not a file" in err
    assert "Traceback" not in err


def test_a_nested_set_keeps_the_fields_own_defaults():
    """``--set sampler.n_samples=256`` changes only n_samples: sigma and lambda stay the study's
    own (the field's default instance), not the nested class's defaults."""
    from workbench.sampling.mppi import MPPIConfig
    from workbench.study.runner import resolve_config
    from workbench.study.spec import registry

    spec = registry()["navigation"]
    base = resolve_config(spec, "tiny")
    cfg = resolve_config(spec, "tiny", sets=["sampler.n_samples=256"])
    assert cfg.sampler.n_samples == 256
    assert (cfg.sampler.sigma, cfg.sampler.lam) == (base.sampler.sigma, base.sampler.lam)
    assert (cfg.sampler.sigma, cfg.sampler.lam) != (MPPIConfig().sigma, MPPIConfig().lam)
