"""What a user hands a command, checked before the command allocates anything or opens a connection.

One check per kind of input, shared by every command and service process: a Zenoh endpoint (:func:`endpoint`), a
file to read (:func:`input_file`, :func:`read_text`), a path to write (:func:`output_file`, :func:`output_dir`), a
count (:func:`at_most`) and a number of seconds or a rate (:func:`finite`). Each refuses with a ``ValueError`` whose
text is one line starting with the field's name (``listen: port 99999 out of range 0..65535``); the CLI prints it
after ``morph-sim <command>: error:`` and exits with status 2.

Nothing here writes or keeps anything: a path to write is probed with a temporary file that is gone at once, and a
file to read is looked at (its kind and size) before a byte of it is read.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
import stat
import tempfile
from pathlib import Path

#: Largest file a command reads whole: a fault schedule, a network profile, a sweep file, a Zenoh config. They are
#: written by hand or by a short script: the largest the project ships is a few kB, and a schedule of
#: MAX_SCHEDULE_ENTRIES entries of ~300 bytes fits three times over. Without a bound, ``/dev/zero`` or a runaway
#: generator's output is read until memory runs out.
MAX_INPUT_FILE_BYTES = 1 << 20

#: The Zenoh transports a run's endpoint may use (the ones its sessions are configured for).
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "unixsock-stream", "ws")
_PORT_RANGE = (0, 65535)  # a TCP/UDP port number is 16 bits; 0 asks the system for a free one (listening only)
_HOST = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9.\-_]*[A-Za-z0-9])?$")  # a host name or an IPv4 address

_KINDS = ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a named pipe"),
          (stat.S_ISSOCK, "a socket"))


def endpoint(value: str, field: str, *, listen: bool = False) -> str:
    """A Zenoh endpoint ``<protocol>/<host>:<port>`` (``unixsock-stream/<path>``), optionally followed by Zenoh's
    ``?metadata`` and ``#config``. The port is in 1..65535, or 0..65535 for an endpoint to ``listen`` on (0: any
    free port). Returns ``value`` unchanged."""
    example = f"{value!r} is not a Zenoh endpoint like tcp/127.0.0.1:7447"
    proto, sep, rest = value.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not sep or proto not in ENDPOINT_PROTOCOLS or not address:
        raise ValueError(f"{field}: {example}")
    if proto == "unixsock-stream":
        return value
    host, colon, port = address.rpartition(":")
    if not colon or not host or not port:
        raise ValueError(f"{field}: {example} (no :port)")
    if host.startswith("["):  # an IPv6 address, [::1]
        try:
            ipaddress.IPv6Address(host[1:-1] if host.endswith("]") else "?")
        except ValueError:
            raise ValueError(f"{field}: {example} ({host} is not an IPv6 address)") from None
    elif not _HOST.match(host):
        raise ValueError(f"{field}: {example} ({host!r} is not a host name or address)")
    if not port.isdigit():
        raise ValueError(f"{field}: port {port!r} of {value!r} is not a number")
    low, high = (_PORT_RANGE[0] if listen else 1), _PORT_RANGE[1]
    if not low <= int(port) <= high:
        raise ValueError(f"{field}: port {int(port)} out of range {low}..{high}")
    return value


def input_file(path: str | os.PathLike, field: str, *, limit: int | None = MAX_INPUT_FILE_BYTES) -> Path:
    """``path`` if it is a regular file (not a directory, a device, a pipe) of at most ``limit`` bytes (None: any
    size); nothing of it is read."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise ValueError(f"{field}: cannot read {path}: no such file") from None
    except OSError as exc:
        raise ValueError(f"{field}: cannot read {path}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(info.st_mode):
        raise ValueError(f"{field}: {path} is a directory, not a file")
    if not stat.S_ISREG(info.st_mode):
        raise ValueError(f"{field}: {path} is {_kind(info.st_mode)}, not a regular file")
    if limit is not None and info.st_size > limit:
        raise ValueError(f"{field}: {path} has {info.st_size:,} bytes, more than the {limit:,} a file given here "
                         "may have")
    return path


def read_text(path: str | os.PathLike, field: str, *, limit: int = MAX_INPUT_FILE_BYTES) -> str:
    """The UTF-8 text of the file :func:`input_file` accepts; at most ``limit`` bytes are ever read (a file that
    grows meanwhile, or one whose size the system does not know, is cut off there and refused)."""
    path = input_file(path, field, limit=limit)
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as exc:
        raise ValueError(f"{field}: cannot read {path}: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise ValueError(f"{field}: {path} has more than the {limit:,} bytes a file given here may have")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{field}: {path} is not UTF-8 text (byte {exc.start})") from None


def output_file(path: str | os.PathLike, field: str, *, parents: bool = False) -> Path:
    """``path`` if a file can be written there: it is a regular file or does not exist yet, and its directory
    exists and takes a new file (with ``parents``: its directory exists or can be created, for a writer that
    creates it). Nothing is created."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        info = None
    except OSError as exc:
        raise ValueError(f"{field}: cannot write {path}: {exc.strerror or exc}") from None
    if info is not None and stat.S_ISDIR(info.st_mode):
        raise ValueError(f"{field}: {path} is a directory, not a file")
    if info is not None and not stat.S_ISREG(info.st_mode):
        raise ValueError(f"{field}: {path} is {_kind(info.st_mode)}, not a regular file")
    parent = path.parent
    if parents and not parent.exists():
        output_dir(parent, field)
        return path
    if not parent.exists():
        raise ValueError(f"{field}: cannot write {path}: the directory {parent} does not exist")
    if not parent.is_dir():
        raise ValueError(f"{field}: cannot write {path}: {parent} is not a directory")
    _probe(parent, f"{field}: cannot write {path}")
    if info is not None and not os.access(path, os.W_OK):
        raise ValueError(f"{field}: cannot write {path}: permission denied")
    return path


def output_dir(path: str | os.PathLike, field: str) -> Path:
    """``path`` if it is a directory that takes new files, or can be created as one (its nearest existing ancestor
    is a directory that takes new entries). Nothing is created."""
    path = Path(path)
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing == path and not path.is_dir():
        raise ValueError(f"{field}: {path} exists and is not a directory")
    if not existing.is_dir():
        raise ValueError(f"{field}: cannot create {path}: {existing} is not a directory")
    _probe(existing, f"{field}: cannot write in {path}" if existing == path else f"{field}: cannot create {path}")
    return path


def at_most(count: int, limit: int, field: str, what: str) -> int:
    """``count`` if it is at most ``limit``: ``seeds: 100,000,000 seeds, at most 100,000``."""
    if count > limit:
        raise ValueError(f"{field}: {count:,} {what}, at most {limit:,}")
    return count


def finite(value: float, field: str, *, above: float | None = None, at_least: float | None = None) -> float:
    """``value`` if it is a finite number ``> above`` (or ``>= at_least``): never nan or infinity, which every
    comparison lets through or no timer can wait for."""
    ok = math.isfinite(value) and (above is None or value > above) and (at_least is None or value >= at_least)
    if not ok:
        bound = f"> {above:g}" if above is not None else f">= {at_least:g}" if at_least is not None else ""
        raise ValueError(f"{field}: must be a finite number {bound}, got {value}".replace("  ", " "))
    return value


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "a special file")


def _probe(directory: Path, refusal: str) -> None:
    """Create and drop a temporary file in ``directory``: the one test of 'can I write here' that also holds for
    root, read-only mounts and the kernel's own file systems (/proc, /sys)."""
    try:
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as exc:
        raise ValueError(f"{refusal}: {exc.strerror or exc}") from None
