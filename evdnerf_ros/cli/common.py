"""What every command shares: the parser with the one-line error contract, argparse types for
ranged numbers and sizes, SIGTERM as an interrupt, and one line for OS errors."""

from __future__ import annotations

import argparse
import errno
import signal
import sys
import threading

from ..errors import EvdnerfError

TOPIC_HELP = "event topic inside a bag (default /event_camera/events)"
GEOMETRY_HELP = ("sensor size WxH of a RAW file whose header gives none (neither a geometry line nor a "
                 "known plugin_name), of an HDF5 file without width / height attributes, or of a text file, "
                 "e.g. 640x480")
STRICT_HELP = ("refuse a RAW file that ends inside a word (default: read its complete words, with a warning "
               "naming the byte offset, as a killed recording ends)")
TIME_UNIT_HELP = ("unit of an HDF5 file's events/t when the file has no time_unit attribute, or of a text "
                  "file's whole-number times: ns, us, ms or s (DSEC and v2e write us); never guessed")


class _Parser(argparse.ArgumentParser):
    """argparse with the toolkit's error contract: one line, exit 2."""

    def error(self, message):
        self.exit(2, f"evdnerf: error: {self.prog}: {message} (see {self.prog} --help)\n")


def number(kind=float, *, low=None, high=None, low_open=False):
    """An argparse type: a finite number of `kind` in the documented range (limits.check_number)."""
    from ..limits import check_number

    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        try:
            return check_number(value, "value", low=low, high=high, low_open=low_open)
        except EvdnerfError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("value: ")) from None

    parse.__name__ = kind.__name__          # argparse names the type in its messages
    return parse


def geometry(text: str) -> tuple[int, int]:
    """argparse type of --geometry WxH."""
    from ..limits import check_number

    w, sep, h = str(text).lower().partition("x")
    try:
        if not sep:
            raise ValueError("no 'x' between width and height")
        return (check_number(int(w), "width", low=1, high=65535),
                check_number(int(h), "height", low=1, high=65535))
    except (ValueError, EvdnerfError) as exc:
        raise argparse.ArgumentTypeError(f"expected WxH such as 640x480, got {text!r} ({exc})") from None


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered like Ctrl-C so every `finally` and cleanup handler runs."""


def _on_sigterm(signum, frame):
    signal.signal(signal.SIGTERM, signal.SIG_IGN)   # one clean-up; a second TERM must not cut it short
    raise Terminated()


def _redeliver_swallowed_interrupt(unraisable) -> None:
    """``sys.unraisablehook`` of the CLI. Python runs a signal's handler between any two
    bytecodes, also inside a finalizer (a ``__del__``, a weakref callback such as h5py's
    object registry's); the KeyboardInterrupt / Terminated raised there cannot propagate, so
    Python prints "Exception ignored ... Traceback" and drops it, and the job would run on
    as if never interrupted. Deliver the signal again instead, from a helper thread so that
    it lands once the finalizer is over (one that lands in a finalizer again comes back
    here). Any other unraisable exception is reported as usual."""
    exc = unraisable.exc_value
    if not isinstance(exc, KeyboardInterrupt) or threading.current_thread() is not threading.main_thread():
        sys.__unraisablehook__(unraisable)
        return
    signum = signal.SIGINT
    if isinstance(exc, Terminated):
        signum = signal.SIGTERM
        signal.signal(signal.SIGTERM, _on_sigterm)  # it set SIG_IGN before raising
    threading.Thread(target=_interrupt_main_soon, args=(signum,), name="redeliver-interrupt",
                     daemon=True).start()


def _interrupt_main_soon(signum: int) -> None:
    import _thread
    import time

    time.sleep(0.01)           # let the finalizer (and this thread's start()) finish first
    _thread.interrupt_main(signum)


def os_error_message(exc: OSError) -> str:
    """One line for an OSError: the path, what went wrong, and what would fix it."""
    where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    what = exc.strerror or str(exc)
    hint = {errno.ENOSPC: "free some space or write elsewhere",
            errno.EDQUOT: "free some space or write elsewhere",
            errno.EFBIG: "the file is larger than this system allows; write elsewhere",
            errno.EROFS: "the file system is read-only; write elsewhere",
            errno.EACCES: "check the permissions or choose another path",
            errno.EPERM: "check the permissions or choose another path",
            errno.ENOENT: "check the path",
            errno.EISDIR: "give a file path, not a folder",
            errno.ENOTDIR: "a part of the path is a file, not a folder"}.get(exc.errno)
    return f"{where + ': ' if where else ''}{what}" + (f"; {hint}" if hint else "")


def _fail(message: str) -> int:
    """The one error line (messages quoting a parser's multi-line report are folded) and exit 2."""
    print("evdnerf: error: " + " ".join(message.split()), file=sys.stderr)
    return 2


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings (dropped events, clamped display ranges) as one line each, like errors."""
    print("evdnerf: warning: " + " ".join(str(message).split()), file=sys.stderr)
