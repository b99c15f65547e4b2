"""Hold Ctrl-C (SIGINT) and SIGTERM while a training iteration commits its state.

An interrupt that lands half-way through an optimiser step would leave parameters, moments
and random generators from two different iterations: no checkpoint could be written from
that.  ``DeferredInterrupts`` swaps in a handler that only notes the signal and, on leaving
the block, restores the previous handlers and calls the noted one, so the
``KeyboardInterrupt`` (or the CLI's SIGTERM subclass of it) is raised between iterations.
A second signal during the block is delivered at once (the user insists; the block's
state is then unusable, which the caller tracks).  Only signals whose handler is a Python
callable are held (SIG_DFL / SIG_IGN behave as before), and only in the main thread,
the only one Python delivers signals to.
"""

from __future__ import annotations

import signal
import threading

SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None))
                if s is not None)


class DeferredInterrupts:
    def __init__(self):
        self.saved: dict = {}
        self.active = False
        self.pending = None

    def __enter__(self) -> "DeferredInterrupts":
        self.saved, self.pending = {}, None
        if threading.current_thread() is threading.main_thread():
            for signum in SIGNALS:
                handler = signal.getsignal(signum)
                if callable(handler):
                    self.saved[signum] = handler
                    signal.signal(signum, self._note)
        self.active = True
        return self

    def _note(self, signum, frame) -> None:
        if self.pending is None:
            self.pending = (signum, frame)
            return
        self._restore()
        self.pending = None
        self.saved[signum](signum, frame)

    def _restore(self) -> None:
        if self.active:
            for signum, handler in self.saved.items():
                signal.signal(signum, handler)
            self.active = False

    def __exit__(self, exc_type, exc, tb) -> bool:
        self._restore()
        pending, self.pending = self.pending, None
        if pending is not None and exc_type is None:
            self.saved[pending[0]](*pending)
        return False
