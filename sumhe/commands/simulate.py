"""``sumhe simulate --out DIR --seed N [...]`` writes a simulated drive; ``--errors DIR ...`` measures drives.

A drive is ``DIR/drive.log`` (candump -L), ``DIR/drive.nmea`` (receive-time-prefixed NMEA; ``drive2.nmea`` for
a second antenna), ``DIR/truth.csv`` and ``DIR/scenario.toml``, plus ``vehicle.dbc`` and ``config.toml`` for a
production-like car; ``--settings DIR/scenario.toml`` regenerates it byte for byte (options given as well
override the file). ``--profile realistic`` draws every real-car error from the seed (default ``kind``: today's
drives). ``--outage 60+10`` is an outage of 10 s from 60 s. ``--errors`` prints the sensor errors of existing
drive directories against their truth, decoded with sumhe's own CAN and NMEA decoders; ``--study-real LOG ...
--gps-dbc FILE`` measures a real logger drive's sensors (:mod:`sumhe.sim.study`).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from sumhe.commands.options import outage
from sumhe.errors import ConfigError, SourceError
from sumhe.sim import load_settings, simulate, write_drive
from sumhe.sim.measure import format_table, measure_errors
from sumhe.sim.profiles import PROFILES, profile_settings
from sumhe.sim.settings import GPS_ERROR_MODELS, OUTAGE_STYLES, SCENARIO_NAMES, SimSettings

_OVERRIDES = {
    "seed": "seed",
    "duration": "duration_s",
    "scenario": "scenario",
    "outage": "outages",
    "outage_style": "outage_style",
    "gps_error": "gps_error",
    "gps_error_m": "gps_error_m",
    "gps_rate": "gps_rate_hz",
    "multipath": "multipath_per_min",
    "antennas": "antennas",
    "antenna_distance": "antenna_distance_m",
    "truth_rate": "truth_rate_hz",
    "can_drop_rate": "can_drop_rate",
}
"""Command-line option (dest) -> SimSettings field."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--out", type=Path, metavar="DIR", help="write the drive's files into DIR")
    action.add_argument("--errors", type=Path, nargs="+", metavar="DIR", help="print the errors of drive directories")
    action.add_argument(
        "--study-real", type=Path, nargs="+", metavar="LOG", help="measure a real logger drive's sensors"
    )
    parser.add_argument("--gps-dbc", type=Path, metavar="FILE", help="--study-real: the logger's GNSS/IMU DBC")
    parser.add_argument(
        "--imu-yaw", default="gnss_imu.AngularRateX", metavar="MSG.SIG", help="--study-real: the yaw-rate signal"
    )
    parser.add_argument("--settings", type=Path, metavar="FILE", help="start from a scenario.toml")
    parser.add_argument(
        "--profile", choices=tuple(PROFILES), help="kind (default: today's drives) or realistic (real-car errors)"
    )
    parser.add_argument("--seed", type=int, metavar="N", help="random seed (default 0)")
    parser.add_argument("--duration", type=float, metavar="S", help="length of the drive in s (default 240)")
    parser.add_argument("--scenario", choices=SCENARIO_NAMES, help="route and driving style (default urban)")
    parser.add_argument("--outage", type=outage, nargs="+", metavar="START+LEN", help="GPS outages, s from the start")
    parser.add_argument("--outage-style", choices=OUTAGE_STYLES, help="silent receiver or 'no fix' sentences")
    parser.add_argument("--gps-error", choices=GPS_ERROR_MODELS, help="GPS error model (default walk)")
    parser.add_argument("--gps-error-m", type=float, metavar="M", help="scale of the GPS error model (m)")
    parser.add_argument("--gps-rate", type=float, metavar="HZ", help="GPS fixes per second (default 10)")
    parser.add_argument("--multipath", type=float, metavar="PER_MIN", help="multipath jumps of 5-50 m per minute")
    parser.add_argument("--antennas", type=int, choices=(1, 2), help="GPS antennas (2: drive2.nmea and HDT)")
    parser.add_argument("--antenna-distance", type=float, metavar="M", help="distance between the antennas (m)")
    parser.add_argument("--truth-rate", type=float, metavar="HZ", help="truth.csv samples per second (default 100)")
    parser.add_argument("--can-drop-rate", type=float, metavar="P", help="fraction of CAN frames lost (default 0)")


def settings_from_args(args: argparse.Namespace) -> SimSettings:
    """The SimSettings of the command line; ConfigError naming the field when a value is out of range."""
    overrides = {field: getattr(args, dest) for dest, field in _OVERRIDES.items() if getattr(args, dest) is not None}
    if "outages" in overrides:
        overrides["outages"] = tuple(overrides["outages"])
    if args.settings is not None and args.profile is not None:
        raise ConfigError("simulate: --profile: give either --settings or --profile (a scenario.toml holds its draws)")
    try:
        if args.settings is not None:
            base = load_settings(args.settings)
        else:
            base = profile_settings(args.profile or "kind", overrides.get("seed", 0))
        return dataclasses.replace(base, **overrides)
    except ValueError as e:
        raise ConfigError(f"simulate: {e}") from e


def run(args: argparse.Namespace) -> int:
    if args.errors:
        return _errors(args.errors)
    if args.study_real:
        return _study(args)
    settings = settings_from_args(args)
    drive = simulate(settings)
    try:
        paths = write_drive(drive, args.out)
    except OSError as e:
        raise ConfigError(f"simulate: --out {args.out}: cannot write: {e.strerror or e}") from e
    epochs = drive.gps[0]
    print(
        f"wrote {args.out}: {settings.scenario} seed {settings.seed}, {settings.duration_s:g} s, "
        f"{float(drive.applied['distance_m']) / 1000:.2f} km, {len(drive.can_frames)} CAN frames, "
        f"{int(epochs.sent.sum())} GPS epochs sent ({int((~epochs.valid).sum())} in outages); "
        f"{', '.join(p.name for p in paths)}"
    )
    return 0


def _study(args: argparse.Namespace) -> int:
    from sumhe.sim.study import format_study, study_real

    if args.gps_dbc is None:
        raise ConfigError("simulate: --study-real needs --gps-dbc FILE (the logger's GNSS/IMU DBC)")
    try:
        rows = study_real(args.study_real, args.gps_dbc, args.imu_yaw)
    except KeyError as e:
        raise SourceError(f"simulate: --study-real: no {e} frames in the logs (is --gps-dbc the logger's?)") from e
    print(format_study(rows, f"== {len(args.study_real)} log(s) from {args.study_real[0]}"))
    return 0


def _errors(dirs: list[Path]) -> int:
    for d in dirs:
        print(format_table(measure_errors(d), f"== {d}"))
    return 0
