"""The command line's whole wall time: from the process's start, not from the command's own start.

The commands time their own work (``... s wall``), which leaves out the Python start-up and the
imports (JAX among them, about a second) that a user waits for too. `process_elapsed` measures from
the process's start as the kernel recorded it (Linux: ``/proc/self/stat``); elsewhere from the
moment this module was first imported (the start of the command line, after ``import jaxsleigh``).
"""
from __future__ import annotations

import os
import time

__all__ = ["process_elapsed", "whole_wall_line"]

# fallback origin: taken when the command line is first imported
_T0 = time.monotonic()


def process_elapsed() -> tuple[float, str]:
    """``(seconds, what)``: wall time since the process started and what that origin is."""
    try:
        with open("/proc/self/stat") as f:
            # the command name (field 2) may hold spaces: split after its closing parenthesis;
            # starttime is field 22, the 20th after it, in clock ticks since boot
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0), "since the process started"
    except (OSError, ValueError, IndexError, AttributeError):
        return time.monotonic() - _T0, "since the command line was imported (its imports of jaxsleigh and JAX excluded)"


def whole_wall_line(prog: str, command: str) -> str:
    """``'jaxsleigh simulate: 7.31 s wall in all since the process started (Python start-up, ...)'``."""
    secs, origin = process_elapsed()
    return (f"{prog} {command}: {secs:.2f} s wall in all {origin} (Python start-up, imports, compilation, "
            f"computing and writing)")
