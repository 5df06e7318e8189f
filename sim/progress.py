"""Progress on stderr, on a terminal and in a log file alike (the CLI contract, DESIGN.md).

On a terminal: a tqdm bar. Otherwise (nohup, CI, a pipe): one plain line every `interval` seconds
(`HYDRABENCH_PROGRESS_S`, default 5) and one at the end, e.g.

    generate: 40/160 frame (25%), 12 s elapsed, ~36 s left

`progress(total, desc)` returns an object with tqdm's `update`, `set_postfix`, `close` and
iteration (`progress(iterable=rows, desc=...)`); `enabled=False` prints nothing.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable


def _interval() -> float:
    try:
        return max(0.0, float(os.environ.get("HYDRABENCH_PROGRESS_S", "5")))
    except ValueError:
        return 5.0


class LineProgress:
    """tqdm's interface, printing a whole line every `interval` seconds (for files and pipes)."""

    def __init__(self, total: int | None = None, desc: str = "", unit: str = "it", initial: int = 0,
                 iterable: Iterable | None = None, interval: float | None = None, stream=None, enabled: bool = True):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.initial = initial  # done before this bar started (a resumed run): not in its rate
        self.interval = _interval() if interval is None else interval
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.t0 = time.monotonic()
        self.last = self.t0
        self.postfix = ""
        self.closed = False
        self.printed = 0
        self.shown = None  # (n, postfix) of the last line printed

    def _line(self) -> str:
        elapsed = time.monotonic() - self.t0
        if self.total:
            text = f"{self.desc}: {self.n}/{self.total} {self.unit} ({100 * self.n / self.total:.0f}%)"
        else:
            text = f"{self.desc}: {self.n} {self.unit}"
        text += f", {elapsed:.0f} s elapsed"
        done = self.n - self.initial
        if self.total and done > 0 and self.n < self.total:
            text += f", ~{elapsed / done * (self.total - self.n):.0f} s left"
        return text + (f", {self.postfix}" if self.postfix else "")

    def _emit(self) -> None:
        if self.enabled:
            self.stream.write(self._line() + "\n")
            self.stream.flush()
            self.printed += 1
            self.shown = (self.n, self.postfix)
        self.last = time.monotonic()

    def update(self, n: int = 1) -> None:
        self.n += n
        if time.monotonic() - self.last >= self.interval:
            self._emit()

    def set_postfix(self, **kw) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in kw.items())

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if self.shown == (self.n, self.postfix):
                return  # the last line already says where it ended
            if self.printed or time.monotonic() - self.t0 >= self.interval:
                self._emit()

    def __iter__(self):
        for item in self.iterable or ():
            yield item
            self.update(1)
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress(total: int | None = None, desc: str = "", unit: str = "it", initial: int = 0,
             iterable: Iterable | None = None, enabled: bool = True):
    """A progress reporter on stderr: tqdm on a terminal, `LineProgress` otherwise."""
    if enabled and sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, file=sys.stderr,
                    dynamic_ncols=True)
    return LineProgress(total=total, desc=desc, unit=unit, initial=initial, iterable=iterable, enabled=enabled)
