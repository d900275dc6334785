"""Is the run's endpoint ready? Before anything starts, the embedded endpoint's port must be free (or, with
``--endpoint``, a router must listen there); after the sim starts, its port must accept connections before anyone
else connects. Only TCP endpoints are probed; others are left to Zenoh."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from services.supervisor.children import Child
from services.supervisor.errors import StartError


def tcp_address(endpoint: str) -> tuple[str, int] | None:
    """Host (IPv6 brackets removed) and port of a ``tcp/host:port`` endpoint; None for any other."""
    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    if proto != "tcp" or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def check_port_free(endpoint: str) -> None:
    """The endpoint's port must be ours to listen on: if another program holds it, the wait for the sim's port
    would connect to that program and the run would fail later with a misleading reason."""
    import socket

    address = tcp_address(endpoint)
    if address is None:
        return
    host, port = address
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise StartError(f"port {port} of {endpoint} (--listen) is not free: {exc.strerror}; another "
                             "program holds it; choose another port or leave --listen out") from None


async def tcp_reachable(endpoint: str, timeout: float) -> bool:
    """Something accepts connections at ``endpoint`` within ``timeout`` seconds."""
    address = tcp_address(endpoint)
    if address is None:
        return True
    host, port = address
    deadline = time.monotonic() + timeout
    while True:
        try:
            _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), 0.5)
            writer.close()
            return True
        except (OSError, asyncio.TimeoutError):
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(0.1)


async def wait_endpoint(sim: Child, endpoint: str, timeout: float, stopping: Callable[[], bool]) -> None:
    """Until the sim's endpoint accepts a connection; StartError if the sim ends first or ``timeout`` seconds pass.
    ``stopping()``: a stop was asked for, so waiting is over."""
    host, _, port = endpoint.partition("/")[2].rpartition(":")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not sim.alive():
            raise StartError(f"sim exited with status {sim.proc.returncode} before opening {endpoint}:\n"
                             f"{sim.log_tail()}")
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(host, int(port)), 0.5)
            writer.close()
            try:
                await writer.wait_closed()
            except Exception:
                pass
            return
        except (OSError, asyncio.TimeoutError):
            await asyncio.sleep(0.05)
        if stopping():
            return
    raise StartError(f"sim did not open {endpoint} within {timeout:.0f} s:\n{sim.log_tail()}")
