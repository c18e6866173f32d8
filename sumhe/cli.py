"""The ``sumhe`` command line: one module per subcommand under :mod:`sumhe.commands`, imported lazily.

Each subcommand module provides ``add_arguments(parser)`` and ``run(args) -> int``; only the module of the
command being run is imported, so ``sumhe nmea`` never loads the solver.
Errors sumhe raises on purpose print ``error: ...`` and exit 1; ``--debug`` shows the traceback.

Logging: warnings and errors by default; a command module may set ``LOG_INFO_FROM``, logger name prefixes whose
INFO lines it shows by default (the daemon's start-up, ready, status and stop lines). ``-v`` is INFO and
``--debug`` DEBUG for every logger (python-can's too); both are accepted before or after the command name.

Exit: the console script (:func:`script`, also ``python -m sumhe``) exits with the code :func:`main` returns; a
command module may set ``EXIT_AT_ONCE = True`` (a command that has closed what it wrote when it returns and leaves
no thread or child process behind): the script then ends the process at once (:func:`end_process`), without the
interpreter's teardown. :func:`main` called in a process (the tests) always returns.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from sumhe import __version__
from sumhe.errors import SumheError, printable
from sumhe.service.collector import young_collections_every

COMMANDS: dict[str, tuple[str, str]] = {
    "nmea": ("sumhe.commands.nmea", "decode NMEA sentences into fixes (JSON lines)"),
    "candump": ("sumhe.commands.candump", "decode a CAN log with the configured DBC mapping (JSON lines)"),
    "record": ("sumhe.commands.record", "record live CAN frames and NMEA lines for later replay"),
    "simulate": ("sumhe.commands.simulate", "simulate a drive (CAN log, NMEA, truth) or measure a drive's errors"),
    "demo": ("sumhe.commands.demo", "the bundled drive through the full live path, no hardware needed"),
    "run": ("sumhe.commands.run", "the daemon: CAN bus + serial GNSS in, positions over UDP out"),
    "can-up": ("sumhe.commands.can_up", "bring up the configured SocketCAN interface (vcan: create it; can: bitrate)"),
    "listen": ("sumhe.commands.listen", "print the positions sumhe sends over UDP (JSON or NMEA)"),
    "play": ("sumhe.commands.play", "play a recorded drive onto a CAN bus and a pseudo-terminal (real time)"),
    "replay": ("sumhe.commands.replay", "run an estimator on a recorded CAN log + NMEA log (JSON lines out)"),
    "fleet": ("sumhe.commands.fleet", "reprocess many recorded drives on Ray: per-drive results and a fleet table"),
    "calibrate": ("sumhe.commands.calibrate", "GNSS time offset, CAN scales and bias of a car from a recorded drive"),
    "protocol": ("sumhe.commands.protocol", "paper 000's outage protocol on simulated drives: errors per method"),
    "bench": ("sumhe.commands.bench", "benchmarks: estimators side by side (default), MHE (mhe), paper 000 (protocol)"),
    "plot": ("sumhe.commands.plot", "PNG of replays: trajectory, outages, error, window length, bounds"),
}


def pin_blas_threads() -> None:
    """Pin BLAS to one thread before numpy/casadi load: IPOPT ran ~25x slower per iteration without."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


WITHOUT_MF4 = frozenset({"replay", "run", "can-up", "listen", "record", "play", "demo", "nmea", "plot"})
"""The commands that read no CAN log but the ones their command line names (the live ones none)."""


def skip_mf4_reader(argv: Sequence[str]) -> None:
    """For a command of :data:`WITHOUT_MF4` whose command line names no MF4 file: load python-can without its MF4
    reader's asammdf and the pandas that comes with it (``sumhe can-up`` 0.85-0.91 -> 0.28-0.35 s and 96 -> 34 MB,
    the daemon's peak memory 204 -> 159 MB, a tenth of a replay of the bundled drive). python-can imports its MF4
    reader at ``import can`` and leaves it unusable (``asammdf`` None) where asammdf cannot be imported: here it
    cannot while python-can loads, and nothing of this process reads or writes MF4. Any other command (``bench
    --drive``, ``fleet`` and ``calibrate`` may find MF4 logs in a folder), or one naming a ``.mf4`` file, loads
    python-can as it is."""
    command = next((a for a in argv if a in COMMANDS), None)
    if command not in WITHOUT_MF4 or any(a.lower().endswith(".mf4") for a in argv) or "can" in sys.modules:
        return
    sys.modules["asammdf"] = None  # type: ignore[assignment]  # `import asammdf` raises ImportError
    try:
        import can  # noqa: F401
    finally:
        del sys.modules["asammdf"]


def _log_flags(parser: argparse.ArgumentParser, default: object) -> None:
    parser.add_argument("--debug", action="store_true", default=default, help="show tracebacks and debug logging")
    parser.add_argument("-v", "--verbose", action="store_true", default=default, help="info-level logging")


def build_parser(argv: Sequence[str] = ()) -> argparse.ArgumentParser:
    """The parser; the arguments of a subcommand are added only if ``argv`` names it."""
    parser = argparse.ArgumentParser(
        prog="sumhe",
        description="Vehicle position through GPS outages: GPS + CAN fused by a state-uniform estimator.",
    )
    parser.add_argument("--version", action="version", version=f"sumhe {__version__}")
    _log_flags(parser, False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, text) in COMMANDS.items():
        p = sub.add_parser(name, help=text, description=text)
        _log_flags(p, argparse.SUPPRESS)  # after the command too; given nowhere, the top-level False stands
        if name in argv:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(
                _run=module.run,
                _log_info_from=getattr(module, "LOG_INFO_FROM", ()),
                _exit_at_once=getattr(module, "EXIT_AT_ONCE", False),
            )
    return parser


def configure_logging(args: argparse.Namespace) -> None:
    """WARNING (INFO with ``-v``, DEBUG with ``--debug``) for every logger, and INFO for the loggers the command
    names in ``LOG_INFO_FROM`` (a handler filter: no logger keeps a level of its own after ``main`` returns)."""
    level = logging.DEBUG if args.debug else logging.INFO if args.verbose else logging.WARNING
    prefixes: tuple[str, ...] = args._log_info_from
    own = logging.INFO if prefixes and level > logging.INFO else level
    logging.basicConfig(level=own, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True)
    if own < level:
        logging.getLogger().handlers[0].addFilter(lambda r: r.levelno >= level or r.name.startswith(prefixes))


def main(argv: Sequence[str] | None = None, *, exit_at_once: bool = False) -> int:
    """Run the command line ``argv`` (default: the process's); returns the process exit code. With
    ``exit_at_once`` (:func:`script`) a command whose module sets ``EXIT_AT_ONCE`` ends the process instead
    (:func:`end_process`)."""
    pin_blas_threads()
    argv = list(sys.argv[1:] if argv is None else argv)
    with young_collections_every():  # the imports' objects live on: collecting them every 700 was 40-60 ms
        skip_mf4_reader(argv)
        parser = build_parser(argv)
    args = parser.parse_args(argv)
    configure_logging(args)
    code = _run(args)
    if exit_at_once and args._exit_at_once:
        end_process(code)
    return code


def script() -> NoReturn:
    """The ``sumhe`` console script and ``python -m sumhe``: :func:`main` on the command line, then exit."""
    sys.exit(main(exit_at_once=True))


def end_process(code: int) -> NoReturn:
    """End the process now with exit status ``code``, the log handlers and the standard streams flushed first:
    without the interpreter's teardown, which frees the objects one by one, module by module, and collects the
    cycles once more (after a replay of the bundled drive ~0.1 s of CPU, a thirtieth of the whole command), and
    without ``atexit`` handlers other than logging's (none other is registered by the commands that use it). The
    way mypy ends its command line. A reader gone (``| head``) or a stream closed is not an error here, as in
    :func:`main`."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(BrokenPipeError, ValueError):
            stream.flush()
    os._exit(code)


def _run(args: argparse.Namespace) -> int:
    """The command's exit code; errors sumhe raises on purpose printed (module docstring)."""
    try:
        return int(args._run(args))
    except SumheError as e:
        if args.debug:
            raise
        text = "\n".join(printable(line, 4000) for line in str(e).splitlines())
        print(f"error: {text}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (e.g. `sumhe nmea LOG | head`): not our error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
