"""The drive simulator: determinism, motion limits, CAN and NMEA decoding back to the truth, outages, files, CLI."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import can
import cantools
import numpy as np
import pynmea2
import pytest

from sumhe.cli import main
from sumhe.io.checksum import is_intact, rolling_counter
from sumhe.sim import SimSettings, Truth, bundled_drive_dir, load_settings, load_truth, simulate, write_drive
from sumhe.sim.can_frames import MIN_WHEEL_SPEED_MPS, TYRE_DEVIATION, wheel_speeds
from sumhe.sim.drive import DRIVE_FILES
from sumhe.sim.routes import SCENARIOS
from sumhe.sim.settings import settings_to_toml
from sumhe.sim.vehicle import WHEELBASE_M

REPO = Path(__file__).resolve().parents[1]
DBC = REPO / "dbc" / "sumhe_ref.dbc"
OUTAGES = ((30.0, 5.0), (60.05, 10.0))
QUIET_CAN = {"can_jitter_s": 0.0, "can_burst_per_min": 0.0}
"""CAN timing without host jitter or bursts: the host timestamp is at most 1 ms after the bus time."""


@pytest.fixture(scope="module")
def urban() -> object:
    return simulate(SimSettings(scenario="urban", seed=1, duration_s=120.0, outages=OUTAGES, outage_style="nofix"))


@pytest.fixture(scope="module", params=sorted(SCENARIOS))
def any_scenario(request: pytest.FixtureRequest) -> object:
    return simulate(SimSettings(scenario=request.param, seed=5, duration_s=200.0, truth_rate_hz=100.0))


@pytest.fixture(scope="module")
def quiet_can(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, Path]:
    drive = simulate(SimSettings(seed=2, duration_s=90.0, gps_error="uniform", gps_error_m=2.0, **QUIET_CAN))
    out = tmp_path_factory.mktemp("quiet")
    write_drive(drive, out)
    return drive, out


# --- settings --------------------------------------------------------------------------------------------------


def test_settings_are_normalised_and_resolve_the_error_scale() -> None:
    s = SimSettings(duration_s=60, outages=((10, 5),), gps_error="rtk")
    assert isinstance(s.duration_s, float)
    assert s.outages == ((10.0, 5.0),)
    assert s.gps_error_scale_m == 0.03
    assert SimSettings(gps_error_m=2.5).gps_error_scale_m == 2.5


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"scenario": "moon"}, "scenario"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"duration_s": 0.0}, "duration_s"),
        ({"duration_s": math.nan}, "duration_s"),
        ({"duration_s": True}, "duration_s"),
        ({"datum_lat_deg": 91.0}, "datum_lat_deg"),
        ({"gps_rate_hz": 50.0}, "gps_rate_hz"),
        ({"gps_rate_hz": 3.0}, "gps_rate_hz"),
        ({"gps_error": "laser"}, "gps_error"),
        ({"gps_error_m": 0.0}, "gps_error_m"),
        ({"multipath_per_min": -1.0}, "multipath_per_min"),
        ({"multipath_min_m": 10.0, "multipath_max_m": 5.0}, "multipath_max_m"),
        ({"outages": ((10.0,),)}, "outages"),
        ({"outages": (10.0, 5.0)}, "outages"),
        ({"outages": ((10.0, 0.0),)}, "outages"),
        ({"outages": ((500.0, 5.0),)}, "outages"),
        ({"outages": ((-1.0, 5.0),)}, "outages"),
        ({"outage_style": "loud"}, "outage_style"),
        ({"gps_latency_s": -0.1}, "gps_latency_s"),
        ({"antennas": 3}, "antennas"),
        ({"antenna_distance_m": 0.0}, "antenna_distance_m"),
        ({"speed_scale": 2.0}, "speed_scale"),
        ({"yaw_rate_bias_dps": 10.0}, "yaw_rate_bias_dps"),
        ({"yaw_rate_noise_dps": -0.1}, "yaw_rate_noise_dps"),
        ({"can_drop_rate": 1.0}, "can_drop_rate"),
        ({"can_jitter_s": "fast"}, "can_jitter_s"),
        ({"truth_rate_hz": 1.0}, "truth_rate_hz"),
    ],
)
def test_bad_settings_raise_naming_the_field(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SimSettings(**kwargs)  # type: ignore[arg-type]


def test_scenario_toml_round_trip(tmp_path: Path) -> None:
    s = SimSettings(scenario="offroad", seed=9, outages=((10.0, 2.5),), gps_error="rtk", antennas=2, speed_scale=1.01)
    path = tmp_path / "scenario.toml"
    path.write_text(settings_to_toml(s, {"note": 'quote " and \\ back'}), encoding="utf-8")
    assert load_settings(path) == s


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[sim]\nwarp = 9\n", "sim.warp: unknown key"),
        ("[sim]\nseed = 'one'\n", "sim.seed"),
        ("[sim]\ngps_rate_hz = 100.0\n", "gps_rate_hz"),
        ("[other]\n", "no \\[sim\\] table"),
        ("[sim\n", "cannot read scenario"),
    ],
)
def test_bad_scenario_files_raise_naming_the_file(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "scenario.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError, match=message) as err:
        load_settings(path)
    assert str(path) in str(err.value)


def test_missing_scenario_file_raises_value_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="cannot read scenario"):
        load_settings(tmp_path / "nope.toml")


# --- determinism ------------------------------------------------------------------------------------------------


def test_same_seed_same_bytes_other_seed_other_drive(tmp_path: Path) -> None:
    settings = SimSettings(scenario="offroad", seed=4, duration_s=40.0, outages=((10.0, 5.0),), antennas=2)
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    written = write_drive(simulate(settings), a)
    write_drive(simulate(settings), b)
    write_drive(simulate(dataclasses.replace(settings, seed=5)), c)
    assert sorted(p.name for p in written) == sorted([*DRIVE_FILES, "drive2.nmea"])
    for p in written:
        assert p.read_bytes() == (b / p.name).read_bytes(), p.name
    assert (a / "drive.log").read_bytes() != (c / "drive.log").read_bytes()
    assert (a / "truth.csv").read_bytes() != (c / "truth.csv").read_bytes()


def test_outages_change_nothing_but_the_gps_in_them(urban: object) -> None:
    other = simulate(dataclasses.replace(urban.settings, outages=()))
    assert np.array_equal(urban.truth.east, other.truth.east)
    assert [m.data for m in urban.can_frames] == [m.data for m in other.can_frames]
    kept = {f.time_utc: f for f in other.fixes()}
    for fix in urban.fixes():
        if fix.valid:
            assert kept[fix.time_utc] == fix


# --- motion -----------------------------------------------------------------------------------------------------


def _scenario(drive: object) -> str:
    return drive.settings.scenario  # type: ignore[no-any-return]


def test_truth_stays_within_the_motion_limits(any_scenario: object) -> None:
    truth, limits = any_scenario.truth, SCENARIOS[_scenario(any_scenario)].limits
    assert truth.speed.min() >= 0.0
    assert truth.speed.max() <= min(40.0, limits.speed_mps) + 1e-9
    assert truth.speed.max() > 0.5 * limits.speed_mps
    assert truth.accel.max() <= limits.accel_mps2 + 1e-6
    assert truth.accel.min() >= -limits.brake_mps2 - 1e-6
    lat_accel = truth.speed * truth.yaw_rate
    assert np.abs(lat_accel).max() <= 1.02 * limits.lat_accel_mps2
    assert np.abs(truth.steering).max() < math.radians(35.0)
    steering_rate = np.diff(truth.steering) * any_scenario.settings.truth_rate_hz
    assert np.abs(steering_rate).max() <= 1.02 * limits.steer_rate_rps
    np.testing.assert_allclose(truth.yaw_rate, truth.speed * np.tan(truth.steering) / WHEELBASE_M, atol=1e-12)
    assert (truth.speed == 0.0).sum() > 100  # starts at standstill for a few seconds at least


def test_truth_satisfies_the_kinematic_model(any_scenario: object) -> None:
    """d(east)/dt = v sin(phi), d(north)/dt = v cos(phi), d(phi)/dt = -yaw_rate, between samples."""
    truth = any_scenario.truth
    h = np.diff(truth.t)
    v = (truth.speed[1:] + truth.speed[:-1]) / 2
    phi = np.unwrap(truth.azimuth)
    mid = (phi[1:] + phi[:-1]) / 2
    brake = SCENARIOS[_scenario(any_scenario)].limits.brake_mps2
    tol = brake * h.max() / 2 + 1e-3  # v is piecewise linear; the mean of the ends differs by a*h/2 at a kink
    assert np.abs(np.diff(truth.east) / h - v * np.sin(mid)).max() < tol
    assert np.abs(np.diff(truth.north) / h - v * np.cos(mid)).max() < tol
    yaw = (truth.yaw_rate[1:] + truth.yaw_rate[:-1]) / 2
    assert np.abs(np.diff(phi) / h + yaw).max() < 0.01
    assert np.abs(np.diff(phi) / h + yaw).mean() < 1e-4


@pytest.mark.parametrize(
    ("scenario", "expected"),
    [
        ("urban", {"roundabout", "stop", "stop-and-go", "lane change", "bend", "intersection turn"}),
        ("highway", {"on-ramp", "lane change", "bend"}),
        ("offroad", {"hairpin", "sharp turn", "slalom", "loop"}),
    ],
)
def test_routes_have_the_features_of_their_scenario(scenario: str, expected: set[str]) -> None:
    drive = simulate(SimSettings(scenario=scenario, seed=0, duration_s=300.0, truth_rate_hz=10.0))
    features = {item.rsplit(" at ", 1)[0] for item in str(drive.applied["route"]).split(", ")}
    assert expected <= features


def test_truth_at_interpolates_and_wraps_the_azimuth() -> None:
    t = np.array([0.0, 1.0, 2.0])
    ones = np.ones(3)
    truth = Truth(t, ones, ones, t, t, np.array([6.2, 0.05, 0.1]), ones, ones, ones, ones, ones, ones)
    at = truth.at([0.5, 1.5, 5.0])
    np.testing.assert_allclose(at.east, [0.5, 1.5, 2.0])
    mid = (6.2 + 0.05 + 2 * math.pi) / 2 - 2 * math.pi
    np.testing.assert_allclose(at.azimuth, [mid % (2 * math.pi), 0.075, 0.1])
    assert float(truth.at(1.0).east) == 1.0
    with pytest.raises(ValueError, match="lat"):
        Truth(t, ones[:2], ones, t, t, t, ones, ones, ones, ones, ones, ones)


def test_truth_csv_round_trip(quiet_can: tuple[object, Path]) -> None:
    drive, out = quiet_can
    loaded = load_truth(out / "truth.csv")
    for name, value in drive.truth.columns().items():
        np.testing.assert_allclose(getattr(loaded, name), value, atol=1e-4, rtol=0, err_msg=name)
    assert loaded.east2 is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("t,lat\n1,2\n", "missing truth columns"),
        ("", "missing truth columns"),
        ("t,lat,lon,east,north,azimuth,speed,yaw_rate,accel,steering,speed_scale,yaw_rate_bias\n", "no truth rows"),
        ("t,lat,lon,east,north,azimuth,speed,yaw_rate,accel,steering,speed_scale,yaw_rate_bias\n1,2\n", "per row"),
        ("t,lat,lon,east,north,azimuth,speed,yaw_rate,accel,steering,speed_scale,yaw_rate_bias\n" + "1," * 11 + "x\n",
         "cannot read"),
        ("t,lat,lon,east,north,azimuth,speed,yaw_rate,accel,steering,speed_scale,yaw_rate_bias\n" + "1," * 11 + "1\n"
         + "1," * 11 + "1\n", "increasing"),
    ],
)  # fmt: skip
def test_bad_truth_files_raise_naming_the_file(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "truth.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ValueError, match=message) as err:
        load_truth(path)
    assert str(path) in str(err.value)
    with pytest.raises(ValueError, match="cannot read"):
        load_truth(tmp_path / "missing.csv")


# --- CAN --------------------------------------------------------------------------------------------------------


def _decoded(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every signal of every frame of a candump log, decoded by python-can + cantools directly."""
    db = cantools.database.load_file(str(DBC))
    rows: dict[str, list[tuple[float, float]]] = {}
    for msg in can.LogReader(path):
        for name, value in db.decode_message(msg.arbitration_id, msg.data, decode_choices=False).items():
            rows.setdefault(name, []).append((msg.timestamp, float(value)))
    return {name: tuple(np.array(r).T) for name, r in rows.items()}  # type: ignore[misc]


def test_can_log_decodes_back_to_the_truth(quiet_can: tuple[object, Path]) -> None:
    drive, out = quiet_can
    s = drive.settings
    decoded = _decoded(out / "drive.log")
    truth = drive.truth
    scale = float(truth.speed_scale[0])
    assert 0.98 <= scale <= 0.99 or 1.01 <= scale <= 1.02

    t, kmh = decoded["VEHICLE_SPEED"]
    lag = s.can_sensor_delay_s + 0.0005  # sensor delay + half the USB frame
    at = truth.at(t - lag)
    err = kmh / 3.6 - at.speed * scale
    moving = at.speed * scale > MIN_WHEEL_SPEED_MPS + 0.05
    # noise + quantisation (0.01 km/h) + up to 0.5 ms of timing at <= 3 m/s^2
    assert np.abs(err[moving]).max() < 5 * s.speed_noise_mps + 0.01 / 3.6 + 3.0 * 0.0006
    assert abs(err[moving].mean()) < 0.003
    assert err[moving].std() == pytest.approx(s.speed_noise_mps, rel=0.15)
    assert np.all(kmh[at.speed == 0.0] == 0.0)

    t, dps = decoded["YAW_RATE"]
    at = truth.at(t - lag)
    err = np.radians(dps) - at.yaw_rate - at.yaw_rate_bias
    assert np.abs(err).max() < math.radians(5 * s.yaw_rate_noise_dps + 0.01)
    assert err.std() == pytest.approx(math.radians(s.yaw_rate_noise_dps), rel=0.15)
    assert abs(err.mean()) < math.radians(0.01)
    assert abs(math.degrees(float(at.yaw_rate_bias.mean()))) <= 0.5 + 0.1

    t, rl = decoded["WHEEL_SPEED_RL"]
    rr = decoded["WHEEL_SPEED_RR"][1]
    fl, fr = decoded["WHEEL_SPEED_FL"][1], decoded["WHEEL_SPEED_FR"][1]
    at = truth.at(t - lag)
    true_wheels = wheel_speeds(at.speed * scale, at.yaw_rate)
    fast = at.speed > 3.0
    for name, measured, expected in zip(("FL", "FR", "RL", "RR"), (fl, fr, rl, rr), true_wheels, strict=True):
        rel = measured[fast] / 3.6 / expected[fast] - 1.0
        assert abs(np.median(rel)) < 4 * TYRE_DEVIATION, name
    turning = fast & (np.abs(at.yaw_rate) > 0.2)
    assert np.all(np.sign(fr[turning] - fl[turning]) == np.sign(at.yaw_rate[turning]))  # outer wheel faster

    t, angle = decoded["STEERING_ANGLE"]
    np.testing.assert_allclose(angle, np.degrees(truth.at(t - lag).steering) * 15.0, atol=0.05 + 0.2)


def test_can_frames_are_protected_counted_and_timed(quiet_can: tuple[object, Path]) -> None:
    drive, _ = quiet_can
    db = cantools.database.load_file(str(DBC))
    stamps = np.array([m.timestamp for m in drive.can_frames])
    assert np.all(np.diff(stamps) > 0)
    assert stamps[0] >= drive.settings.start_unix_s
    assert stamps[-1] <= drive.settings.start_unix_s + drive.settings.duration_s + 0.01
    for name in ("ESP_YAW_RATE", "ESP_VEHICLE_SPEED"):
        message = db.get_message_by_name(name)
        frames = [m for m in drive.can_frames if m.arbitration_id == message.frame_id]
        assert all(is_intact(bytes(m.data)) for m in frames)
        counters = np.array([rolling_counter(bytes(m.data)) for m in frames])
        assert np.all(np.diff(counters) % 16 == 1)
        periods = np.diff([m.timestamp for m in frames])
        cycle = message.cycle_time / 1000.0
        assert np.median(periods) == pytest.approx(cycle, abs=2e-4)
        assert np.abs(periods - cycle).max() < 0.0015  # no bursts, no host jitter: the USB frame only
        assert len(frames) == pytest.approx(drive.settings.duration_s / cycle, abs=2)
    assert drive.can_frames[0].channel == "can0"


def test_can_bursts_and_drops() -> None:
    settings = SimSettings(seed=3, duration_s=60.0, can_burst_per_min=30.0, can_burst_max_s=0.05, can_drop_rate=0.2)
    drive = simulate(settings)
    full = simulate(dataclasses.replace(settings, can_drop_rate=0.0))
    assert len(drive.can_frames) / len(full.can_frames) == pytest.approx(0.8, abs=0.02)
    yaw = [m for m in full.can_frames if m.arbitration_id == 0x130]
    gaps = np.diff([m.timestamp for m in yaw])
    assert gaps.max() > 0.02  # a stall held frames back ...
    assert (gaps < 0.002).sum() >= 3  # ... and they arrived in a burst
    counters = np.array([rolling_counter(bytes(m.data)) for m in drive.can_frames if m.arbitration_id == 0x130])
    assert np.any(np.diff(counters) % 16 > 1)  # the receiver sees the lost frames


def test_can_samples_match_sumhe_decoder(quiet_can: tuple[object, Path]) -> None:
    can_io = pytest.importorskip("sumhe.io.can")
    from sumhe.config import SignalSpec

    drive, out = quiet_can
    signals = {q: SignalSpec(*name.split(".")) for q, name in can_io.REFERENCE_SIGNALS.items()}
    decoder = can_io.CanDecoder(can_io.load_dbc(DBC), signals, can_io.REFERENCE_E2E)
    decoded = [s for msg in can_io.read_log(out / "drive.log") for s in decoder.decode(msg)]
    mine = drive.can_samples()
    assert len(decoded) == len(mine) > 0
    assert decoder.stats.crc_errors == decoder.stats.frames_lost == decoder.stats.stale == 0
    for a, b in zip(decoded, mine, strict=True):
        assert (a.t, a.quantity) == (b.t, b.quantity)
        assert a.value == pytest.approx(b.value, abs=1e-12)


# --- GPS --------------------------------------------------------------------------------------------------------


def _parse_nmea(lines: list[str]) -> list[tuple[float, pynmea2.NMEASentence]]:
    out = []
    for line in lines:
        prefix, text = line.split(" ", 1)
        out.append((float(prefix[1:-1]), pynmea2.parse(text, check=True)))
    return out


def _fix_time(drive: object, msg: pynmea2.NMEASentence) -> float:
    start = drive.settings.start_unix_s
    day = start - start % 86400
    ts = msg.timestamp
    return day + ts.hour * 3600 + ts.minute * 60 + ts.second + ts.microsecond / 1e6


def test_nmea_parses_back_to_the_truth_within_the_uniform_bound(quiet_can: tuple[object, Path]) -> None:
    drive, out = quiet_can
    lines = (out / "drive.nmea").read_text(encoding="ascii").splitlines()
    assert lines == drive.nmea_lines
    gga = [(rx, m) for rx, m in _parse_nmea(lines) if m.sentence_type == "GGA"]
    assert len(gga) == len(drive.gps[0].t_fix) == drive.settings.duration_s * 10 + 1
    t_fix = np.array([_fix_time(drive, m) for _, m in gga])
    height = [m.altitude + float(m.geo_sep) for _, m in gga]  # ellipsoidal, as the frame's datum
    enu = drive.frame.to_enu([m.latitude for _, m in gga], [m.longitude for _, m in gga], height)
    at = drive.truth.at(t_fix)
    assert np.abs(enu[:, 2]).max() < 1.5 * drive.settings.gps_error_scale_m + 1e-3
    bound = drive.settings.gps_error_scale_m + 1e-3
    assert np.abs(enu[:, 0] - at.east).max() < bound
    assert np.abs(enu[:, 1] - at.north).max() < bound
    assert np.abs(enu[:, 0] - at.east).max() > 0.9 * bound  # the box is used, not just its middle
    latency = np.array([rx for rx, _ in gga]) - t_fix
    s = drive.settings
    assert latency.min() >= s.gps_latency_s
    assert latency.max() <= s.gps_latency_s + s.gps_latency_jitter_s + 0.01  # + the GGA's serial time


def test_fixes_match_what_the_decoders_read(urban: object) -> None:
    rmc = [m for _, m in _parse_nmea(urban.nmea_lines) if m.sentence_type == "RMC"]
    fixes = urban.fixes()
    assert len(rmc) == len(fixes)
    for fix, msg in zip(fixes, rmc, strict=True):
        assert fix.valid == (msg.status == "A")
        if fix.valid:
            assert fix.lat_deg == pytest.approx(msg.latitude, abs=1e-12)
            assert fix.speed_mps == pytest.approx(msg.spd_over_grnd * 1852 / 3600, abs=1e-12)
    nmea_io = pytest.importorskip("sumhe.io.nmea")
    decoded = list(nmea_io.iter_fixes(urban.nmea_lines))
    assert len(decoded) == len(fixes)
    for a, b in zip(decoded, fixes, strict=True):
        assert (a.t, a.time_utc, a.valid, a.quality, a.sats, a.course_rad) == (
            b.t, b.time_utc, b.valid, b.quality, b.sats, b.course_rad
        )  # fmt: skip
        for name in ("lat_deg", "lon_deg", "alt_m", "speed_mps", "sigma_lat_m"):
            assert getattr(a, name) == pytest.approx(getattr(b, name), abs=1e-12), name


@pytest.mark.parametrize("style", ["silence", "nofix"])
def test_outages_appear_exactly_where_asked(urban: object, style: str) -> None:
    drive = simulate(dataclasses.replace(urban.settings, outage_style=style)) if style == "silence" else urban
    start = drive.settings.start_unix_s
    fixes = {round(f.time_utc.timestamp() - start, 2): f for f in drive.fixes()}
    epochs = np.round(drive.gps[0].t_fix - start, 2)
    for a, length in OUTAGES:
        inside = epochs[(epochs >= a) & (epochs < a + length)]
        assert len(inside) == round(length * 10)
        for e in inside:
            assert e not in fixes if style == "silence" else not fixes[e].valid
        before, after = inside[0] - 0.1, inside[-1] + 0.1
        assert fixes[round(before, 2)].valid and fixes[round(after, 2)].valid
        assert drive.in_outage(start + inside[0]) and not drive.in_outage(start + before)
    n_valid = sum(f.valid for f in fixes.values())
    assert n_valid == len(epochs) - 150
    if style == "nofix":
        nofix = [m for _, m in _parse_nmea(drive.nmea_lines) if m.sentence_type == "GGA" and m.gps_qual == 0]
        assert len(nofix) == 150
        assert all(m.lat == "" for m in nofix)
    else:
        assert len(drive.fixes()) == n_valid


def test_course_is_held_at_standstill(urban: object) -> None:
    fixes = [f for f in urban.fixes() if f.valid]
    at = urban.truth.at([f.time_utc.timestamp() for f in fixes])
    first_motion = int(np.argmax(at.speed > 1.0))
    assert all(f.course_rad is None for f in fixes[:first_motion] if f.speed_mps < 0.5)
    last = None
    for fix, v in zip(fixes[first_motion:], at.speed[first_motion:], strict=True):
        if fix.speed_mps < 0.5:
            assert fix.course_rad == last
        else:
            last = fix.course_rad
        if v == 0.0:
            assert fix.speed_mps < 0.25


@pytest.mark.parametrize(
    ("model", "scale"),
    [("gaussian", 1.5), ("walk", 1.0), ("rtk", 0.03)],
)
def test_gps_error_models(model: str, scale: float) -> None:
    gps_error_m = scale if model == "gaussian" else None
    drive = simulate(
        SimSettings(seed=7, duration_s=600.0, gps_error=model, gps_error_m=gps_error_m, truth_rate_hz=10.0)
    )
    e = drive.gps[0].error_east
    fixes = drive.fixes()
    assert all(f.sigma_lat_m == pytest.approx(scale / (math.sqrt(3) if model == "rtk" else 1), abs=1e-3) for f in fixes)
    ten_second_means = e[:6000].reshape(60, 100).mean(axis=1)
    if model == "gaussian":
        assert e.std() == pytest.approx(scale, rel=0.1)
        assert ten_second_means.std() < 0.2 * scale  # white: averages out
    elif model == "walk":
        assert ten_second_means.std() > 0.4 * scale  # a random walk: does not average out within 10 s
        assert e.std() == pytest.approx(scale, rel=0.5)
    else:
        assert np.abs(e).max() <= 0.03
        assert {f.quality for f in fixes} == {4}
        assert all(line.endswith("R*" + line[-2:]) for line in drive.nmea_lines if "RMC" in line)


def test_multipath_jumps() -> None:
    settings = SimSettings(seed=8, duration_s=120.0, gps_error="uniform", multipath_per_min=5.0, truth_rate_hz=10.0)
    jumpy = simulate(settings).gps[0]
    e = np.hypot(jumpy.error_east, jumpy.error_north)
    assert e.max() > 5.0 - 1.5
    assert e.max() <= 50.0 * 3 + 1.5
    clean = simulate(dataclasses.replace(settings, multipath_per_min=0.0)).gps[0]
    assert np.hypot(clean.error_east, clean.error_north).max() <= math.sqrt(2.0)


def test_two_antennas(tmp_path: Path) -> None:
    settings = SimSettings(scenario="offroad", seed=2, duration_s=60.0, antennas=2, antenna_distance_m=1.2,
                           gps_error="rtk", outages=((20.0, 5.0),))  # fmt: skip
    drive = simulate(settings)
    truth = drive.truth
    assert truth.east2 is not None and truth.north2 is not None
    np.testing.assert_allclose(np.hypot(truth.east - truth.east2, truth.north - truth.north2), 1.2, atol=1e-9)
    paths = write_drive(drive, tmp_path)
    assert (tmp_path / "drive2.nmea").read_text(encoding="ascii").splitlines() == drive.nmea_lines2
    assert tmp_path / "drive2.nmea" in paths
    assert not any("HDT" in line for line in drive.nmea_lines2)
    heading = [f for f in drive.fixes(1) if f.heading_rad is not None]
    assert len(heading) == sum(f.valid for f in drive.fixes(1))
    err = [(f.heading_rad - truth.at(f.time_utc.timestamp()).azimuth + math.pi) % (2 * math.pi) - math.pi
           for f in heading]  # fmt: skip
    assert np.degrees(np.std(err)) == pytest.approx(settings.heading_sigma_deg, rel=0.2)
    second = [f for f in drive.fixes(2) if f.valid]
    at = truth.at([f.time_utc.timestamp() for f in second])
    enu = drive.frame.to_enu([f.lat_deg for f in second], [f.lon_deg for f in second], [f.alt_m + 45.0 for f in second])
    assert np.abs(enu[:, 0] - at.east2).max() < 0.031
    assert np.abs(enu[:, 1] - at.north2).max() < 0.031
    assert load_truth(tmp_path / "truth.csv").north2 is not None
    with pytest.raises(ValueError, match="antenna"):
        drive.fixes(3)


# --- command line and bundled drive --------------------------------------------------------------------------------


def test_cli_simulate_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "d"
    args = ["simulate", "--out", str(out), "--seed", "2", "--duration", "30", "--scenario", "offroad"]
    assert main([*args, "--outage", "10+5", "20+2.5", "--gps-error", "rtk", "--truth-rate", "20"]) == 0
    assert "wrote" in capsys.readouterr().out
    assert load_settings(out / "scenario.toml").outages == ((10.0, 5.0), (20.0, 2.5))
    again = tmp_path / "again"
    assert main(["simulate", "--out", str(again), "--settings", str(out / "scenario.toml")]) == 0
    for name in DRIVE_FILES:
        assert (out / name).read_bytes() == (again / name).read_bytes(), name
    capsys.readouterr()
    assert main(["simulate", "--errors", str(out)]) == 0
    table = capsys.readouterr().out
    assert "CAN speed - true speed" in table
    assert "GPS1 horizontal position error" in table
    row = next(line for line in table.splitlines() if line.startswith("GPS1 horizontal position error"))
    assert float(row.split()[-1]) < 0.05  # rtk: a few cm at most


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--gps-rate", "50"], "gps_rate_hz"),
        (["--duration", "-5"], "duration_s"),
        (["--outage", "100+5", "--duration", "50"], "outages"),
        (["--settings", "/nonexistent/scenario.toml"], "cannot read scenario"),
    ],
)
def test_cli_bad_values_print_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    assert main(["simulate", "--out", str(tmp_path), *argv]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "drive.log").exists()


@pytest.mark.parametrize("argv", [["--outage", "10-5"], ["--outage", "x+1"], ["--scenario", "moon"], []])
def test_cli_bad_syntax_exits_with_usage(tmp_path: Path, argv: list[str]) -> None:
    out = [] if not argv else ["--out", str(tmp_path)]
    with pytest.raises(SystemExit) as err:
        main(["simulate", *out, *argv])
    assert err.value.code == 2


def test_cli_out_that_cannot_be_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory", encoding="utf-8")
    assert main(["simulate", "--out", str(blocker / "drive"), "--duration", "5"]) == 1
    assert "cannot write" in capsys.readouterr().err


def test_cli_errors_of_a_missing_drive(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "--errors", str(tmp_path)]) == 1
    assert "truth.csv" in capsys.readouterr().err
    assert main(["simulate", "--out", str(tmp_path), "--duration", "5", "--truth-rate", "10"]) == 0
    (tmp_path / "drive.nmea").write_bytes(b"\x00garbage\n$GPGGA,bad*00\n")
    (tmp_path / "drive.log").unlink()
    assert main(["simulate", "--errors", str(tmp_path)]) == 1
    assert "drive.log" in capsys.readouterr().err
    (tmp_path / "drive.log").write_text("(1.0) can0 nonsense\n", encoding="ascii")
    assert main(["simulate", "--errors", str(tmp_path)]) == 0  # nothing decodable: empty rows, no crash
    assert "CAN speed - true speed" in capsys.readouterr().out


def test_bundled_drive_is_shipped_and_regenerates_byte_for_byte(tmp_path: Path) -> None:
    bundled = bundled_drive_dir()
    settings = load_settings(bundled / "scenario.toml")
    assert 180.0 <= settings.duration_s <= 300.0
    assert len(settings.outages) == 2
    assert settings.gps_rate_hz == 10.0
    assert sum((bundled / name).stat().st_size for name in DRIVE_FILES) < 6_000_000
    text = (bundled / "scenario.toml").read_text(encoding="utf-8")
    assert "roundabout" in text and "stop" in text
    write_drive(simulate(settings), tmp_path)
    for name in DRIVE_FILES:
        assert (bundled / name).read_bytes() == (tmp_path / name).read_bytes(), name
