"""A Ctrl-C to `generate --workers N` is never lost (`sensors.generate._ctrl_c_as_flag`).

Python raises KeyboardInterrupt wherever the main thread is when the SIGINT handler runs; inside a
finalizer it is printed as "Exception ignored" and dropped, and the command ran on to exit 0 (seen
once in `make test`'s Ctrl-C test under load). While the pool runs, the handler only sets a flag."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

import pytest

from sensors.generate import _ctrl_c_as_flag


class _SignalsInItsFinalizer:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs here, inside the finalizer


def test_a_ctrl_c_inside_a_finalizer_is_kept_and_raised_when_the_pool_is_done():
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        with _ctrl_c_as_flag() as flag:
            _SignalsInItsFinalizer()  # dropped at once: its finalizer sends the SIGINT
            time.sleep(0.05)
            assert flag.is_set()  # kept, not raised (nor lost) inside the finalizer
    assert signal.getsignal(signal.SIGINT) is before  # the handler is restored


def test_without_the_flag_the_same_ctrl_c_is_lost(monkeypatch):
    """The failure the flag prevents: with Python's own handler the interrupt is raised inside the
    finalizer, handed to sys.unraisablehook ("Exception ignored") and the program goes on."""
    ignored = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: ignored.append(u.exc_type))
    _SignalsInItsFinalizer()
    time.sleep(0.05)  # reached: no KeyboardInterrupt here
    assert ignored == [KeyboardInterrupt]


def test_no_ctrl_c_no_interrupt_and_other_threads_leave_the_handler_alone():
    with _ctrl_c_as_flag() as flag:
        pass
    assert not flag.is_set()
    seen = {}

    def other():
        with _ctrl_c_as_flag() as f:
            seen["handler"] = signal.getsignal(signal.SIGINT)
            seen["set"] = f.is_set()

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert seen == {"handler": signal.default_int_handler, "set": False}
