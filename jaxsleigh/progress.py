"""A progress bar for long host-side loops (tqdm when available and wanted, otherwise silent)."""
from __future__ import annotations

import sys

__all__ = ["Progress"]


class Progress:
    """Context manager with ``update(fraction_done)`` and ``postfix(name=value, ...)``; ``enabled=None``
    means 'on a terminal'.

    Until the first progress is reported the bar says "compiling": the first call of a jitted
    kernel compiles it (seconds), which is otherwise a bar frozen at 0 %.
    """

    def __init__(self, enabled=None, desc: str = "", unit: str = "%"):
        if enabled is None:
            enabled = sys.stderr.isatty()
        self._bar = None
        if enabled:
            try:
                from tqdm.auto import tqdm
            except ImportError:  # pragma: no cover - tqdm is a dependency
                tqdm = None
            if tqdm is not None:
                self._bar = tqdm(total=1000, desc=f"{desc} (compiling)", unit="", bar_format=(
                    "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]"))
        self._desc = desc
        self._last = 0

    def update(self, fraction: float) -> None:
        if self._bar is None:
            return
        now = int(round(1000 * min(max(fraction, 0.0), 1.0)))
        if now > 0 and self._last == 0:
            self._bar.desc = self._desc
        if now > self._last:
            self._bar.update(now - self._last)
            self._last = now

    def postfix(self, **values) -> None:
        """Show ``name=value`` pairs after the times (e.g. the tuner's loss); shown with the next update."""
        if self._bar is not None:
            self._bar.set_postfix(values, refresh=False)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._bar is not None:
            if exc[0] is None:
                self.update(1.0)
            self._bar.close()
        return False
