"""The `evdnerf` command: one subcommand per job, one module per command group.

Bad input prints one line `evdnerf: error: ...` and exits with status 2; outputs are written
atomically, so a failed command leaves nothing half-written.  Each group module has
``register(subparsers)``; plugins (rig's `flash` and `servo`) register through the entry points
`evdnerf.commands` the same way.
"""

from __future__ import annotations

import signal
import sys
import threading
import warnings

from .. import __version__
from ..errors import EvdnerfError
from . import calibrate, events, ros, session, simulate, train
from .common import (Terminated, _fail, _on_sigterm, _Parser, _redeliver_swallowed_interrupt, _show_warning,
                     geometry, number, os_error_message)

__all__ = ["main", "run", "build_parser", "number", "geometry", "Terminated", "os_error_message"]

GROUPS = (simulate, events, session, train, ros, calibrate)


def build_parser() -> _Parser:
    parser = _Parser(
        prog="evdnerf",
        description="EvDNeRF rig toolkit: event files and bags, simulation of the virtual rig, sync, "
                    "training and event publishing.")
    parser.add_argument("--version", action="version", version=f"evdnerf {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for group in GROUPS:
        group.register(sub)
    # Plugins (e.g. rig's `flash` and `servo`): entry points `evdnerf.commands`, each a
    # function register(subparsers) adding sub-parsers with set_defaults(func=...).
    from importlib.metadata import entry_points

    for ep in entry_points(group="evdnerf.commands"):
        ep.load()(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:            # --help (0) or a bad flag (2, one line printed): a status
        return exc.code if isinstance(exc.code, int) else 2
    warnings.showwarning = _show_warning
    hook = sys.unraisablehook
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)
        sys.unraisablehook = _redeliver_swallowed_interrupt
    try:
        return args.func(args)
    except EvdnerfError as exc:
        return _fail(str(exc))
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):         # `evdnerf info x | head`: not an error
            return 0
        return _fail(os_error_message(exc))
    except MemoryError:
        return _fail("out of memory; use a smaller input, window or resolution")
    except Terminated:
        print("evdnerf: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("evdnerf: interrupted", file=sys.stderr)
        return 130
    finally:
        sys.unraisablehook = hook


def run() -> None:
    """The `evdnerf` executable (and ``python -m evdnerf_ros``): ``main`` as the process's exit.

    An interrupted job (exit 130 / 143) has removed its partial outputs and closed what it
    wrote before ``main`` returns, and then leaves without the interpreter's teardown. A signal
    can land inside h5py's own bookkeeping (its object registry's callbacks), and the
    interpreter's final garbage collection then crashed on the half-updated objects: SIGSEGV
    instead of 130 / 143, 4 in 22 interrupted converts on a loaded machine."""
    code = main()
    if code in (130, 143):
        import os

        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    raise SystemExit(code)
