"""Check a Dask scheduler address before a run writes anything.

:func:`check_scheduler` accepts ``[protocol://]host:port`` (protocol tcp, tls, ws, wss or ucx;
a bare ``host:port`` means tcp; IPv6 hosts in brackets) and ``inproc://...`` (a scheduler in
this process); anything else is refused at once. For tcp, tls, ws and wss it then opens (and
closes) a TCP connection to the scheduler's port, name lookup included, within ``timeout``
seconds (default :data:`CONNECT_TIMEOUT_S`), so that a wrong host or port, a scheduler that is
not running or a firewall fails within seconds instead of the client's own timeout. For tcp it
also waits (within the same time) for the first bytes of the scheduler's greeting, which a Dask
scheduler sends as soon as a connection opens: a port where something else listens and stays
silent would otherwise make the client wait for ever. This module does not import
``distributed``.
"""

from __future__ import annotations

import re
import socket
import threading
import time
from typing import Any

from workbench.study.config_io import ConfigError

CONNECT_TIMEOUT_S = 5.0
PROTOCOLS = ("tcp", "tls", "ws", "wss", "ucx")
_ADDRESS = re.compile(r"^(?:(?P<proto>[A-Za-z][A-Za-z0-9+.-]*)://)?"
                      r"(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(?P<port>[0-9]{1,5})/?$")
EXAMPLE = "a Dask scheduler address such as tcp://host:8786 (or host:8786)"


class SchedulerError(ConfigError):
    """A scheduler address that is malformed or cannot be reached."""


def parse_scheduler(address: Any) -> tuple[str, str, int]:
    """(protocol, host, port) of an address; raises :class:`SchedulerError` naming it."""
    if not isinstance(address, str) or not address.strip():
        raise SchedulerError(f"scheduler = {address!r} is invalid: must be {EXAMPLE}")
    m = _ADDRESS.match(address.strip())
    if m is None:
        raise SchedulerError(f"scheduler = {address!r} is invalid: must be {EXAMPLE}")
    proto = (m["proto"] or "tcp").lower()
    if proto not in PROTOCOLS:
        raise SchedulerError(f"scheduler = {address!r} is invalid: the protocol {proto!r} is "
                             f"not a Dask protocol ({', '.join(PROTOCOLS)}); must be {EXAMPLE}")
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise SchedulerError(f"scheduler = {address!r} is invalid: the port {port} is not in "
                             f"1..65535; must be {EXAMPLE}")
    return proto, m["host"].strip("[]"), port


class _Silent(Exception):
    pass


def _probe(host: str, port: int, timeout: float, greeting: bool, result: list) -> None:
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            if greeting:
                sock.settimeout(max(deadline - time.monotonic(), 0.1))
                try:
                    if not sock.recv(1):
                        raise _Silent("it closed the connection without a greeting")
                except TimeoutError:
                    raise _Silent(f"it accepted the connection but sent no greeting within "
                                  f"{timeout:g} s") from None
            result.append(None)
    except (OSError, _Silent) as exc:  # includes socket.gaierror and TimeoutError
        result.append(exc)


def check_scheduler(address: Any, timeout: float = CONNECT_TIMEOUT_S) -> str:
    """The address (stripped) if it is well formed and, for TCP-based protocols, its port
    accepts a connection within ``timeout`` seconds; else :class:`SchedulerError` saying
    which and what to check."""
    if isinstance(address, str) and address.strip().startswith("inproc://"):
        return address.strip()
    proto, host, port = parse_scheduler(address)
    if proto == "ucx":
        return address.strip()
    result: list = []
    probe = threading.Thread(target=_probe, args=(host, port, timeout, proto == "tcp", result),
                             daemon=True, name="scheduler-probe")
    probe.start()
    probe.join(timeout + 1.0)  # name lookup has no timeout of its own
    if not result:
        reason = f"no answer within {timeout:g} s"
    elif isinstance(result[0], _Silent):
        raise SchedulerError(f"scheduler = {address!r}: something listens at {host}:{port} but "
                             f"it is not a Dask scheduler ({result[0]}); check the port (a "
                             "scheduler listens on 8786 unless told otherwise)")
    elif result[0] is not None:
        exc = result[0]
        reason = (f"no answer within {timeout:g} s" if isinstance(exc, TimeoutError)
                  else getattr(exc, "strerror", None) or str(exc))
    else:
        return address.strip()
    raise SchedulerError(f"scheduler = {address!r}: cannot reach a Dask scheduler at "
                         f"{host}:{port} ({reason}); check that the scheduler is running "
                         "(`dask scheduler`), the host name and port, and that this machine "
                         "may connect to it")
