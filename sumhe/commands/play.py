"""``sumhe play DIR|CANLOG [--nmea NMEALOG] --config FILE``: play a recorded drive onto a CAN bus and a pty.

CAN frames go onto the bus of ``[can]`` in the config (e.g. ``vcan0`` or a ``udp_multicast`` group); NMEA lines
are written into a new pseudo-terminal reachable at ``--pty`` (a symlink), which a service reads as its serial
port (``gps.port``). Runs at real time (``--speed 1``) unless told otherwise. ``--reopen-pty-at S`` closes the
pseudo-terminal S seconds into the drive and opens a new one at the same path (an unplugged receiver);
``--can-silence START+LEN`` stops sending CAN for LEN seconds (a bus that went down).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path

import can

from sumhe.config import load_config, parse_host_port
from sumhe.errors import ConfigError
from sumhe.io.can import read_log
from sumhe.io.player import Player, Pty, TcpNmeaServer, read_nmea_log
from sumhe.sim import bundled_drive_dir

log = logging.getLogger(__name__)


def _span(text: str) -> tuple[float, float]:
    start, sep, length = text.partition("+")
    try:
        return float(start), float(length) if sep else 0.0
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"expected START+LEN seconds, got {text!r}") from e


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "drive", nargs="?", help="a drive directory (drive.log + drive.nmea) or a CAN log (default: the bundled drive)"
    )
    parser.add_argument("--nmea", metavar="NMEALOG", help="NMEA log (default: drive.nmea in the drive directory)")
    parser.add_argument("--config", metavar="FILE", required=True, help="TOML config; its [can] bus is played onto")
    parser.add_argument("--pty", metavar="PATH", default="/tmp/sumhe-gps", help="symlink to the pty (NMEA)")
    parser.add_argument(
        "--nmea-tcp", metavar="HOST:PORT", help="serve the NMEA over TCP instead of a pty (gps.port = socket://...)"
    )
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed factor (1 = real time)")
    parser.add_argument("--no-can", action="store_true", help="play the NMEA only")
    parser.add_argument("--reopen-pty-at", type=float, metavar="S", help="unplug and replug the pty S s in")
    parser.add_argument("--can-silence", type=_span, metavar="START+LEN", help="no CAN frames for LEN s from START")


def _drive_files(args: argparse.Namespace) -> tuple[Path, Path | None]:
    drive = Path(args.drive) if args.drive else bundled_drive_dir()
    if drive.is_dir():
        nmea = Path(args.nmea) if args.nmea else drive / "drive.nmea"
        return drive / "drive.log", nmea if nmea.exists() else None
    return drive, Path(args.nmea) if args.nmea else None


def _at(player: Player, delay_s: float, action) -> threading.Timer:
    timer = threading.Timer(delay_s / player.speed, action)
    timer.daemon = True
    timer.start()
    return timer


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    can_log, nmea_log = _drive_files(args)
    if not can_log.exists():
        raise ConfigError(f"play: no CAN log at {can_log}")
    frames = [] if args.no_can else list(read_log(can_log))
    lines = read_nmea_log(nmea_log) if nmea_log is not None else []
    bus = None
    if not args.no_can:
        kwargs = {**config.can.bus, "interface": config.can.interface, "channel": config.can.channel}
        if config.can.interface == "virtual":
            kwargs["preserve_timestamps"] = True
        bus = can.Bus(**kwargs)
    if not lines:
        pty = None
    elif args.nmea_tcp:
        pty = TcpNmeaServer(*parse_host_port(args.nmea_tcp))
    else:
        pty = Pty(Path(args.pty))
    player = Player(frames, lines, bus, pty, speed=args.speed)
    timers = []
    if args.reopen_pty_at is not None:
        timers.append(_at(player, args.reopen_pty_at, player.reopen_pty))
    if args.can_silence is not None:
        start, length = args.can_silence
        timers.append(_at(player, start, player.paused_can.set))
        timers.append(_at(player, start + length, player.paused_can.clear))
    where = f"tcp {args.nmea_tcp}" if args.nmea_tcp else f"pty at {args.pty}"
    print(f"playing {len(frames)} CAN frames and {len(lines)} NMEA lines; NMEA on {where}", file=sys.stderr)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: player.request_stop())
    player.on_start = lambda: print(
        f"clock offset {player.start_t - player.t0:.6f} s (service time = drive time + offset)",
        file=sys.stderr,
        flush=True,
    )
    try:
        player.run()
    finally:
        for timer in timers:
            timer.cancel()
        if bus is not None:
            bus.shutdown()
        if pty is not None:
            pty.close()
        if isinstance(pty, Pty):
            pty.unlink()
    print(f"played {player.sent_frames} frames, {player.sent_lines} lines", file=sys.stderr)
    return 0
