"""The ``optitac-edge`` command line: the parser and the entry point; each command is a module of
:mod:`optitac_edge.cli.commands`.

Every expected failure (bad recording, bad bundle, frames that don't match)
ends in one line on stderr and exit status 2; Ctrl-C ends a run with status 0.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from optitac_edge import __version__
from optitac_edge.cli.commands import COMMANDS, command, left
from optitac_edge.cli.common import EXIT_ERROR, EXIT_INTERRUPTED, Parser
from optitac_edge.cli.help import describe
from optitac_edge.errors import EXTRA_OF_MODULE, Interrupted, OptiTacError, missing_extra
from optitac_edge.io import interrupts
from optitac_edge.io.logs import NonBlockingLogging

log = logging.getLogger("optitac_edge")


def build_parser() -> argparse.ArgumentParser:
    """The ``optitac-edge`` parser: every command's own (``commands/<name>.py``), in :data:`COMMANDS` order."""
    parser = Parser(prog="optitac-edge", description="OptiTac tactile sensor processing.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _add_verbosity(parser, None)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for name in COMMANDS:
        command(name).add_parser(sub)
    _add_verbosity_to_commands(parser)
    describe(parser)
    return parser


def _add_verbosity(p: argparse.ArgumentParser, default: Any) -> None:
    """-v / -q, accepted before and after the command (``default`` SUPPRESS on the command's parser,
    so it keeps what was given before it)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument("-v", "--verbose", action="count", default=0 if default is None else default,
                       help="more log detail (run: debug)")
    group.add_argument("-q", "--quiet", action="store_true", default=False if default is None else default,
                       help="warnings and errors only")


def _add_verbosity_to_commands(parser: argparse.ArgumentParser) -> None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in dict.fromkeys(action.choices.values()):
                _add_verbosity(command, argparse.SUPPRESS)
                _add_verbosity_to_commands(command)


def _log_level(args: argparse.Namespace) -> int:
    """The service logs its life (INFO) unless -q; -v gives debug. Other commands: warnings, -v info."""
    if args.quiet:
        return logging.WARNING
    if args.command == "run":
        return logging.DEBUG if args.verbose else logging.INFO
    return logging.INFO if args.verbose == 1 else logging.DEBUG if args.verbose > 1 else logging.WARNING


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``optitac-edge`` console script."""
    # One BLAS thread: the per-frame matrix-vector product is small, and worker
    # threads competing with the camera and link threads only add jitter.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    logs = NonBlockingLogging(_log_level(args)).start()  # nothing that logs ever waits on stderr
    # long steps' progress lines (where no bar is shown) unless -q
    logging.getLogger("optitac_edge.progress").setLevel(logging.WARNING if args.quiet else logging.INFO)
    handler = command(args.command).run
    if getattr(args, "fresh", False):  # for the line an interrupt ends with: was a complete recording there?
        from optitac_edge.io.recording_paths import holds_recording

        args.replacing = holds_recording(Path(getattr(args, "out_dir", None) or args.output))
    message, code = None, EXIT_ERROR
    restore = {} if args.command == "run" else _interrupt_on_signals()  # run stops cleanly on its own
    try:
        code = handler(args)
    except OptiTacError as exc:
        message = f"error: {exc}"
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        by = "" if signum == signal.SIGINT else f" by {signal.Signals(signum).name}"
        message, code = f"interrupted{by}: {left(args.command, args)}", 128 + signum
    except OSError as exc:  # e.g. an output path that cannot be written
        where = f"{exc.filename}: " if exc.filename else ""
        message = f"error: {where}{exc.strerror or exc}"
    except ModuleNotFoundError as exc:  # an optional package this feature needs
        if exc.name is None or exc.name.split(".")[0] not in (*EXTRA_OF_MODULE, "picamera2"):
            raise
        message = f"error: {missing_extra(exc.name, f'optitac-edge {args.command}')}"
    except MemoryError:
        message = "error: out of memory"
    finally:
        logs.stop()  # the queued log lines first, then the verdict
        for signum, previous in restore.items():
            signal.signal(signum, previous)
    if message is not None:
        try:
            print(f"{chr(10) if code == EXIT_INTERRUPTED and sys.stderr.isatty() else ''}optitac-edge: {message}",
                  file=sys.stderr)
        except OSError:  # the terminal went with the SSH session
            pass
    return code


def _interrupt_on_signals() -> dict[int, Any]:
    """SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` (a KeyboardInterrupt) in the main thread, once:
    every command then cleans up as on Ctrl-C (``collect`` retracts the tip). A second signal during that
    cleanup is ignored, so it cannot cut a retract short; the first signal during a retract after an error is
    held until the retract is done (:mod:`optitac_edge.io.interrupts`), a second one stops it. A signal ignored at start (``nohup``, a background
    job's SIGINT) stays ignored. Returns the handlers to restore."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    fired: list[int] = []

    def interrupt(signum: int, frame: object) -> None:
        if interrupts.hold(signum):  # a retract under way: it finishes (a second signal stops it)
            return
        if fired:
            return
        fired.append(signum)
        raise Interrupted(signum)

    previous: dict[int, Any] = {}
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, interrupt)
    return previous
