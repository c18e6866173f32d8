"""``sumhe candump LOG [LOG ...] [--config FILE] [--all]``: decode CAN logs with the configured DBC mapping.

Prints one JSON line per decoded sample (``t`` s, ``message``, ``quantity``, ``value`` in SI units; with
``gps.source = "can"`` also one per GNSS fix, ``quantity`` ``"fix"`` and ``value`` the fix as ``sumhe nmea``
prints it, ``t`` its receive time) or, with ``--all``, one line per signal of every DBC message (``t``,
``message``, ``signal``, ``value``, ``unit`` as in the DBC). Several logs of one drive are read as one, in time
order. A summary goes to stderr: frames, per-message rates, decode errors, unused ids and mapped quantities that
gave nothing. Without ``--config`` the reference vehicle's mapping (``dbc/sumhe_ref.dbc``) is used.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable
from typing import TextIO

import can

from sumhe.commands.nmea import fix_to_json
from sumhe.config import load_config
from sumhe.io.can import EXTENDED_FLAG, CanDecoder, DecodeStats, LogStats, read_logs, reference_config
from sumhe.io.replay import beside_logs, paths_of
from sumhe.messages import CanSample, Sample


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "logs", nargs="+", metavar="LOG", help="CAN logs: candump -L .log, .mf4, .asc, .blf, .trc or .csv (or .gz)"
    )
    parser.add_argument(
        "--config", metavar="FILE", help="TOML config with [can] dbc and signals (default: reference vehicle)"
    )
    parser.add_argument(
        "--all", action="store_true", help="print every signal of every DBC message in DBC units instead"
    )


def run(args: argparse.Namespace) -> int:
    logs = paths_of(args.logs)
    config = beside_logs(load_config(args.config) if args.config else reference_config(), logs)
    decoder = CanDecoder.from_config(config, every_message=args.all)
    log_stats = LogStats()
    frames = read_logs(logs, log_stats)
    if args.all:
        _dump_signals(decoder, frames, sys.stdout)
    else:
        _dump_samples(decoder, frames, sys.stdout)
    sys.stdout.flush()
    sys.stderr.write(summary(decoder.stats, log_stats, decoder.silent()))
    return 0


def _dump_samples(decoder: CanDecoder, frames: Iterable[can.Message], out: TextIO) -> None:
    names = decoder.message_names()
    position = decoder.gnss.position if decoder.gnss is not None else ""
    for msg in frames:
        for s in decoder.decode(msg):
            out.write(json.dumps(_sample_line(s, names, position)) + "\n")
    for fix in decoder.flush():
        out.write(json.dumps(_sample_line(fix, names, position)) + "\n")


def _sample_line(s: Sample, names: dict[str, str], position: str) -> dict[str, object]:
    if isinstance(s, CanSample):
        return {"t": s.t, "message": names[s.quantity], "quantity": s.quantity, "value": s.value}
    return {"t": s.t, "message": position, "quantity": "fix", "value": fix_to_json(s)}


def _dump_signals(decoder: CanDecoder, frames: Iterable[can.Message], out: TextIO) -> None:
    units = {(m.name, s.name): s.unit or "" for db in decoder.dbs for m in db.messages for s in m.signals}
    for msg in frames:
        decoded = decoder.decode_signals(msg)
        if decoded is None:
            continue
        name, values = decoded
        for signal, value in values.items():
            line = {"t": msg.timestamp, "message": name, "signal": signal, "value": value, "unit": units[name, signal]}
            out.write(json.dumps(line) + "\n")


def summary(stats: DecodeStats, log_stats: LogStats, silent: Iterable[str] = ()) -> str:
    """The human-readable stderr summary: counters, mean rate of each message over the log span, unused ids,
    and the mapped quantities that gave nothing."""
    duration_s = stats.last_t - stats.first_t
    lines = [
        f"frames: {stats.frames} over {duration_s:.3f} s; decoded {stats.decoded}, unused {stats.unused}, "
        f"decode errors {stats.decode_errors}, CRC errors {stats.crc_errors}, stale {stats.stale}, "
        f"counter jumps {stats.counter_jumps} ({stats.frames_lost} frames lost), error frames {stats.error_frames}, "
        f"remote frames {stats.remote_frames}, FD frames on classic ids {stats.fd_frames}, too long for their "
        f"message {stats.long_frames}, other multiplexer values {stats.other_mux}, "
        f"flagged invalid {stats.invalid}, malformed log lines {log_stats.malformed}, log clock re-based "
        f"{log_stats.rebases} times"
    ]
    if log_stats.files > 1 or len(stats.channels) > 1:
        lines.append(
            f"files: {log_stats.files}; channels: " + ", ".join(f"{c} ({n})" for c, n in stats.channels.items())
        )
    if log_stats.error:
        lines.append(f"log ended early: {log_stats.error}")
    for name, count in sorted(stats.per_message.items()):
        if count:
            rate = f"{count / duration_s:.1f} Hz" if duration_s > 0 else "- Hz"
            lines.append(f"  {name}: {count} frames, {rate}")
    if stats.unused_ids:
        top = sorted(stats.unused_ids.items(), key=lambda kv: -kv[1])[:20]
        ids = ", ".join(f"{_format_id(k)} ({n})" for k, n in top)
        more = f" and {len(stats.unused_ids) - len(top)} more" if len(stats.unused_ids) > len(top) else ""
        lines.append(f"unused ids: {ids}{more}")
    lines += [f"warning: {line}" for line in silent]
    return "\n".join(lines) + "\n"


def _format_id(key: int) -> str:
    return f"0x{key & ~EXTENDED_FLAG:08X}" if key & EXTENDED_FLAG else f"0x{key:03X}"
