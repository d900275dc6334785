"""A child process bound to the life of its parent: the one place that asks the kernel for it.

A parent killed with SIGKILL runs no clean-up of its own, so its children must learn of its death from the kernel:
on Linux ``prctl(PR_SET_PDEATHSIG, sig)`` sends them ``sig`` when the thread that started them ends. The supervisor's
children (``up``), the fork server's and the lab's pool workers all use it.
"""

from __future__ import annotations

import sys

PR_SET_PDEATHSIG = 1  # prctl(2) option, linux/prctl.h


def signal_on_parent_death(sig: int) -> bool:
    """Ask the kernel to send this process ``sig`` when its parent dies; False where it cannot (not Linux, no libc).
    The caller checks ``os.getppid()`` afterwards: a parent that died before the request was made sends nothing."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        return ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
