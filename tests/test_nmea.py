"""The NMEA decoder: sentence types, epoch assembly, dates, bad input, and a property test over arbitrary bytes."""

from __future__ import annotations

import datetime as dt
import math

import pynmea2
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sumhe.cli import main
from sumhe.errors import SourceError
from sumhe.io.nmea import KNOT_MPS, MAX_HELD, RESYNC_AFTER, NmeaCounters, NmeaDecoder, format_log_line, iter_fixes

DATE = dt.date(2024, 5, 17)
UTC = dt.timezone.utc


def nmea(body: str) -> str:
    """``$body*hh`` with a correct checksum."""
    return f"${body}*{pynmea2.NMEASentence.checksum(body):02X}"


def gga(time: str = "120000.00", lat: str = "4807.038,N", lon: str = "01131.000,E", quality: int = 1, talker="GP"):
    return nmea(f"{talker}GGA,{time},{lat},{lon},{quality},08,0.9,545.4,M,46.9,M,,")


def rmc(time: str = "120000.00", status: str = "A", date: str = "170524", talker: str = "GP", mode: str = "A"):
    return nmea(f"{talker}RMC,{time},{status},4807.038,N,01131.000,E,10.0,84.4,{date},3.1,W,{mode}")


def decode(*lines: str | bytes, date: dt.date | None = DATE) -> tuple[list, NmeaCounters]:
    dec = NmeaDecoder(date=date)
    fixes = [f for line in lines for f in dec.feed(line)]
    fixes += dec.flush()
    assert_consistent(dec.counters)
    return fixes, dec.counters


def assert_consistent(c: NmeaCounters) -> None:
    assert c.fragments == c.sentences + c.checksum_errors + c.garbled
    assert c.unknown + c.late <= c.sentences
    assert c.comments <= c.lines
    assert c.no_fix <= c.fixes <= c.sentences
    assert min(vars(c).values()) >= 0


LAT = 48 + 7.038 / 60
LON = 11 + 31.0 / 60


# --- one sentence type at a time -------------------------------------------------------------------


def test_gga_gives_position_altitude_quality_and_time():
    [fix], c = decode(gga())
    assert fix.valid and fix.quality == 1
    assert fix.lat_deg == pytest.approx(LAT, abs=1e-12) and fix.lon_deg == pytest.approx(LON, abs=1e-12)
    assert fix.alt_m == 545.4 and fix.sats == 8 and fix.hdop == 0.9 and fix.talker == "GP"
    assert fix.time_utc == dt.datetime(2024, 5, 17, 12, 0, 0, tzinfo=UTC)
    assert fix.t == fix.time_utc.timestamp()
    assert fix.speed_mps is None and fix.course_rad is None and fix.heading_rad is None
    assert c.sentences == 1 and c.fixes == 1 and c.no_fix == 0


def test_southern_and_western_hemispheres_are_negative():
    [fix], _ = decode(gga(lat="4552.65403,S", lon="17030.00668,W"))
    assert fix.lat_deg == pytest.approx(-(45 + 52.65403 / 60), abs=1e-12)
    assert fix.lon_deg == pytest.approx(-(170 + 30.00668 / 60), abs=1e-12)


def test_rmc_gives_speed_in_mps_course_in_rad_and_the_date():
    [fix], _ = decode(rmc(date="010203"), date=None)
    assert fix.valid and fix.quality == 1
    assert fix.speed_mps == pytest.approx(10.0 * 1852 / 3600)
    assert fix.course_rad == pytest.approx(math.radians(84.4))
    assert fix.time_utc == dt.datetime(2003, 2, 1, 12, tzinfo=UTC)
    assert fix.alt_m is None and fix.sats is None


def test_rmc_mode_indicator_sets_quality():
    [fix], _ = decode(rmc(mode="D"))
    assert fix.valid and fix.quality == 2


def test_vtg_gives_speed_and_course_when_rmc_is_absent():
    fixes, _ = decode(gga(), nmea("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A"))
    assert fixes[0].speed_mps == pytest.approx(5.5 * KNOT_MPS)
    assert fixes[0].course_rad == pytest.approx(math.radians(54.7))


def test_vtg_with_kmh_only_and_vtg_with_mode_n():
    [fix], _ = decode(gga(), nmea("GPVTG,,T,,M,,N,36.0,K,A"))
    assert fix.speed_mps == pytest.approx(10.0) and fix.course_rad is None
    [fix], _ = decode(gga(), nmea("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,N"))
    assert fix.speed_mps is None and fix.course_rad is None


def test_rmc_speed_wins_over_vtg():
    [fix], _ = decode(rmc(), nmea("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A"))
    assert fix.speed_mps == pytest.approx(10.0 * KNOT_MPS)


def test_gst_gives_sigmas_in_metres():
    [fix], _ = decode(gga(), nmea("GPGST,120000.00,004.0,008.7,004.7,132.3,006.8,007.2,00014"))
    assert (fix.sigma_lat_m, fix.sigma_lon_m, fix.sigma_alt_m) == (6.8, 7.2, 14.0)


@pytest.mark.parametrize(
    ("sentence", "heading_deg"),
    [
        ("HEHDT,274.07,T", 274.07),
        ("GPHDT,,T", None),
        ("GNTHS,77.52,A", 77.52),
        ("GNTHS,77.52,V", None),
        ("HEHDT,360.0,T", 0.0),
    ],
)
def test_heading_from_hdt_and_ths(sentence, heading_deg):
    [fix], c = decode(gga(), nmea(sentence))
    expected = None if heading_deg is None else pytest.approx(math.radians(heading_deg))
    assert fix.heading_rad == expected
    assert c.unknown == 0


def test_gsa_hdop_is_only_a_fallback():
    [fix], _ = decode(rmc(), nmea("GNGSA,A,3,03,19,27,13,,,,,,,,,2.75,2.56,1.00"))
    assert fix.hdop == 2.56
    [fix], _ = decode(gga(), nmea("GNGSA,A,3,03,19,27,13,,,,,,,,,2.75,2.56,1.00"))
    assert fix.hdop == 0.9


def test_zda_gives_the_date():
    fixes, _ = decode(nmea("GPZDA,120000.00,31,12,2019,00,00"), gga(), date=None)
    assert fixes[0].time_utc == dt.datetime(2019, 12, 31, 12, tzinfo=UTC)


def test_gll_gives_a_position():
    [fix], _ = decode(nmea("GPGLL,4807.038,N,01131.000,E,120000.00,A,A"))
    assert fix.valid and fix.lat_deg == pytest.approx(LAT) and fix.alt_m is None
    [fix], _ = decode(nmea("GPGLL,4807.038,N,01131.000,E,120000.00,V,N"))
    assert not fix.valid and fix.lat_deg is None


@pytest.mark.parametrize("talker", ["GP", "GN", "GL", "GA", "GB", "BD", "QZ", "GI", "GQ", "HE", "IN"])
def test_any_talker(talker):
    [fix], c = decode(gga(talker=talker))
    assert fix.valid and fix.talker == talker and fix.lat_deg == pytest.approx(LAT)
    assert c.unknown == 0


def test_gps_and_multi_gnss_talkers_of_one_epoch_give_one_fix_with_the_combined_values():
    """Telit PLS83-W: GPGGA (GPS only, 5 sats), GAGGA (Galileo, 1 sat) and GNGNS (all, 14 sats) of one epoch."""
    lines = [
        "$GPGGA,043539.00,4333.190206,N,00127.618380,E,1,05,1.3,250.8,M,50.0,M,,*62",
        "$GAGGA,043539.00,4333.190206,N,00127.618380,E,1,01,1.3,250.8,M,50.0,M,,*77",
        "$GNGNS,043539.00,4333.190206,N,00127.618380,E,AAAAN,14,1.3,250.8,50.0,,,V*62",
        "$GPRMC,043539.00,A,4333.190206,N,00127.618380,E,0.0,,040925,1.7,W,A,V*7C",
    ]
    [fix], c = decode(*lines, date=None)
    assert fix.valid and fix.sats == 14 and fix.talker == "GN" and fix.quality == 1
    assert fix.lat_deg == pytest.approx(43 + 33.190206 / 60, abs=1e-12)
    assert fix.time_utc == dt.datetime(2025, 9, 4, 4, 35, 39, tzinfo=UTC)
    assert c.sentences == 4 and c.fixes == 1


def test_gn_verdict_decides_when_a_single_constellation_has_no_fix():
    [fix], _ = decode(gga(quality=0, lat=",", lon=","), gga(talker="GN"))
    assert fix.valid and fix.talker == "GN"


# --- validity: invalid wins -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "lines",
    [
        pytest.param([rmc(status="V"), gga()], id="rmc-V-gga-1"),
        pytest.param([gga(), rmc(status="V")], id="gga-1-rmc-V"),
        pytest.param([gga(quality=0), rmc()], id="gga-0-rmc-A"),
        pytest.param([rmc(mode="N")], id="rmc-mode-N"),
        pytest.param([gga(quality=6)], id="gga-dead-reckoning"),
        pytest.param([rmc(mode="E")], id="rmc-estimated"),
        pytest.param([gga(lat=",", lon=",")], id="gga-1-empty-position"),
        pytest.param([nmea("GPGGA,120000.00,4807.038,N,01131.000,E,1,00,3.3,545.4,M,,M,,")], id="gga-0-sats"),
        pytest.param([nmea("GNGNS,120000.00,4807.038,N,01131.000,E,NN,05,1.3,250.8,50.0,,")], id="gns-NN"),
        pytest.param([nmea("GPGGA,120000.00,,,,,0,,,,M,,M,,")], id="gga-empty"),
    ],
)
def test_a_fix_without_a_position_is_invalid_and_has_no_coordinates(lines):
    [fix], c = decode(*lines)
    assert not fix.valid
    assert fix.lat_deg is None and fix.lon_deg is None and fix.alt_m is None
    assert fix.quality not in range(1, 6)
    assert c.no_fix == 1


def test_invalid_rmc_contributes_no_speed():
    [fix], _ = decode(rmc(status="V"))
    assert fix.speed_mps is None and fix.course_rad is None


def test_epochs_with_only_timeless_or_date_sentences_give_no_fix():
    fixes, c = decode(nmea("GPZDA,120000.00,17,05,2024,00,00"), nmea("HEHDT,4.0,T"))
    assert fixes == [] and c.sentences == 2


# --- epochs ------------------------------------------------------------------------------------------


def test_sentences_of_one_time_make_one_fix_emitted_when_the_next_time_starts():
    dec = NmeaDecoder(date=DATE)
    assert dec.feed(gga("120000.00")) == []
    assert dec.feed(rmc("120000.00")) == []
    [fix] = dec.feed(gga("120001.00"))
    assert fix.time_utc.second == 0 and fix.alt_m == 545.4 and fix.speed_mps is not None
    [last] = dec.flush()
    assert last.time_utc.second == 1
    assert dec.flush() == []


def test_close_epoch_emits_at_once_and_a_timeless_sentence_after_it_starts_the_next_epoch():
    dec = NmeaDecoder(date=DATE)
    dec.feed(gga("120000.00"))
    [fix] = dec.close_epoch()
    assert fix.heading_rad is None
    dec.feed(nmea("HEHDT,90.0,T"))
    dec.feed(gga("120001.00"))
    [fix] = dec.flush()
    assert fix.heading_rad == pytest.approx(math.pi / 2)
    assert dec.counters.late == 0


def test_a_timeless_sentence_before_the_first_timed_one_joins_its_epoch():
    [fix], _ = decode(nmea("HEHDT,90.0,T"), gga())
    assert fix.heading_rad == pytest.approx(math.pi / 2)


def cycle(second: int) -> list[str]:
    t = f"1200{second:02d}.00"
    return [
        rmc(t),
        gga(t),
        nmea("GPGSA,A,3,03,19,27,13,,,,,,,,,2.75,2.56,1.00"),
        nmea("GPGST," + t + ",1,,,,0.7,0.5,1.1"),
    ]


def test_the_cycle_ender_is_learned_and_then_emits_an_epoch_on_its_last_sentence():
    dec = NmeaDecoder(date=DATE)
    emitted_on = []
    for second in range(6):
        for i, line in enumerate(cycle(second)):
            if dec.feed(line):
                emitted_on.append((second, i))
    # the first epochs end when the next starts (line 0); once GST is known to end the cycle, on GST (line 3)
    assert emitted_on[:2] == [(1, 0), (2, 0)]
    assert emitted_on[-2:] == [(4, 3), (5, 3)]
    assert dec.counters.fixes == 6 and dec.flush() == []


def test_a_late_sentence_is_dropped_and_the_cycle_ender_unlearned():
    dec = NmeaDecoder(date=DATE)
    for second in range(4):
        for line in cycle(second):
            dec.feed(line)
    assert dec.counters.fixes == 4  # the ender (GST) emitted epoch 3 already
    late_gga = gga("120003.00")
    assert dec.feed(late_gga) == []
    assert dec.feed(nmea("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A")) == []  # timeless after an ender: late
    assert dec.counters.late == 2
    dec.feed(rmc("120004.00"))
    dec.feed(nmea("GPGST,120004.00,1,,,,0.7,0.5,1.1"))
    assert dec.counters.fixes == 4  # unlearned: the epoch now waits for the next time
    assert len(dec.feed(rmc("120005.00"))) == 1
    assert_consistent(dec.counters)


def test_the_fix_time_is_the_receive_time_of_the_first_sentence_of_the_epoch():
    lines = [f"(1700000000.250) {gga()}", f"(1700000000.300) {rmc()}", f"(1700000001.250) {gga('120001.00')}"]
    fixes, _ = decode(*lines)
    assert [f.t for f in fixes] == [1700000000.25, 1700000001.25]
    assert fixes[0].time_utc == dt.datetime(2024, 5, 17, 12, tzinfo=UTC)


def test_log_line_format_round_trips():
    line = format_log_line(1700000000.123456, gga().encode() + b"\r\r\n")
    assert line == b"(1700000000.123456) " + gga().encode() + b"\n"
    [fix], _ = decode(line)
    assert fix.t == 1700000000.123456


def test_explicit_receive_time_wins_over_the_prefix():
    dec = NmeaDecoder(date=DATE)
    dec.feed(f"(5.0) {gga()}", t=7.0)
    [fix] = dec.flush()
    assert fix.t == 7.0


# --- time and date ------------------------------------------------------------------------------------


def test_day_rolls_over_at_midnight_without_a_new_date():
    lines = [rmc("235959.00", date="311224"), gga("235959.50"), gga("000000.00"), gga("000000.50")]
    fixes, _ = decode(*lines, date=None)
    assert [f.time_utc for f in fixes] == [
        dt.datetime(2024, 12, 31, 23, 59, 59, tzinfo=UTC),
        dt.datetime(2024, 12, 31, 23, 59, 59, 500000, tzinfo=UTC),
        dt.datetime(2025, 1, 1, 0, 0, 0, tzinfo=UTC),
        dt.datetime(2025, 1, 1, 0, 0, 0, 500000, tzinfo=UTC),
    ]


def test_time_going_backwards_drops_the_epoch_then_follows_a_real_clock_jump():
    lines = [gga("120010.00"), gga("120005.00"), gga("120011.00")]
    fixes, c = decode(*lines)
    assert [f.time_utc.second for f in fixes] == [10, 11]
    assert c.backwards == 1
    jump = [gga(f"1100{s:02d}.00") for s in range(RESYNC_AFTER + 1)]
    fixes, c = decode(gga("120010.00"), *jump)
    assert c.backwards == RESYNC_AFTER - 1
    assert [(f.time_utc.hour, f.time_utc.second) for f in fixes] == [
        (12, 10),
        (11, RESYNC_AFTER - 1),
        (11, RESYNC_AFTER),
    ]


def test_without_a_date_fixes_are_held_until_one_arrives():
    """Two GGA-only epochs before midnight, then an RMC after it: the held fixes get the day before."""
    dec = NmeaDecoder()
    assert dec.feed(gga("235958.00")) == [] and dec.feed(gga("235959.00")) == []
    assert dec.feed(rmc("000000.00", date="010125")) == []
    fixes = dec.feed(gga("000001.00"))
    assert [f.time_utc for f in fixes] == [
        dt.datetime(2024, 12, 31, 23, 59, 58, tzinfo=UTC),
        dt.datetime(2024, 12, 31, 23, 59, 59, tzinfo=UTC),
        dt.datetime(2025, 1, 1, 0, 0, 0, tzinfo=UTC),
    ]
    assert [f.t for f in fixes] == [f.time_utc.timestamp() for f in fixes]


def test_without_any_date_fixes_are_dropped_and_counted():
    fixes, c = decode(gga("120000.00"), gga("120001.00"), date=None)
    assert fixes == [] and c.undated == 2


def test_the_hold_is_bounded():
    fixes, c = decode(*(gga(f"12{m:02d}{s:02d}.00") for m in range(2) for s in range(60)), date=None)
    assert fixes == [] and c.undated == 120
    dec = NmeaDecoder()
    for s in range(MAX_HELD + 5):
        dec.feed(gga(f"12{s // 60:02d}{s % 60:02d}.00"))
    fixes = dec.feed(rmc("130000.00")) + dec.flush()
    assert len(fixes) == MAX_HELD + 1 and dec.counters.undated == 5


def test_without_a_date_but_with_a_receive_time_the_fix_is_emitted_without_utc_time():
    [fix], _ = decode(f"(1700000000.5) {gga()}", date=None)
    assert fix.time_utc is None and fix.t == 1700000000.5 and fix.valid


def test_a_fix_with_no_time_of_its_own():
    [fix], _ = decode(f"(1700000000.5) {nmea('GPGGA,,,,,,0,,,,M,,M,,')}", date=None)
    assert fix.time_utc is None and not fix.valid
    fixes, c = decode(nmea("GPGGA,,,,,,0,,,,M,,M,,"), date=None)
    assert fixes == [] and c.undated == 1


# --- bad input: each kind is counted, never fatal -----------------------------------------------------


GOOD = gga()


@pytest.mark.parametrize(
    ("line", "counter"),
    [
        pytest.param(GOOD[:-2] + ("00" if GOOD[-2:] != "00" else "01"), "checksum_errors", id="bad-checksum"),
        pytest.param(GOOD[:-3], "checksum_errors", id="missing-checksum"),
        pytest.param(GOOD[:30], "checksum_errors", id="truncated"),
        pytest.param("$GPGG", "garbled", id="truncated-type"),
        pytest.param(GOOD[:-1], "garbled", id="one-checksum-digit"),
        pytest.param(gga(lat="48x7.038,N"), "garbled", id="not-a-number"),
        pytest.param(gga(lat="4867.038,N"), "garbled", id="minutes-over-60"),
        pytest.param(gga(lat="9107.038,N"), "garbled", id="latitude-over-90"),
        pytest.param(gga(lat="4807.038,X"), "garbled", id="bad-hemisphere"),
        pytest.param(gga(lat="4807.038,"), "garbled", id="missing-hemisphere"),
        pytest.param(gga(time="126100.00"), "garbled", id="bad-time"),
        pytest.param(nmea("GPGGA,120000,4807.038,N,01131.000,E,1,08,0.9,nan,M,,M,,"), "garbled", id="nan"),
        pytest.param(nmea("GPGGA,120000,4807.038,N,01131.000,E,1,-8,0.9,1,M,,M,,"), "garbled", id="negative"),
        pytest.param(rmc(date="320124"), "garbled", id="bad-date"),
        pytest.param(nmea("GPZDA,120000.00,17,05,0024,00,00"), "garbled", id="zda-year"),
        pytest.param(nmea("GPVTG,inf,T,,M,,N,,K,A"), "garbled", id="infinite"),
        pytest.param(GOOD.replace("545.4", "545é4"), "garbled", id="non-ascii"),
        pytest.param(GOOD.replace("545.4", "545\x014"), "garbled", id="control-char"),
        pytest.param("\xb5b\x01\x07\x5c\x00\x80", "garbled", id="binary"),
        pytest.param("hello world", "garbled", id="text"),
    ],
)
def test_bad_input_is_counted_and_ignored(line, counter, caplog):
    fixes, c = decode(line, gga("120001.00"))
    assert [f.time_utc.second for f in fixes] == [1]
    assert getattr(c, counter) == 1
    assert c.sentences == 1
    assert counter in caplog.text


@pytest.mark.parametrize(
    "line",
    [
        nmea("GPGSV,3,1,12,08,88,068,,07,59,081,24,28,41,187,,05,40,260,"),
        nmea("PFST,FOM,6"),
        nmea("GPXYZ,1,2,3"),
        nmea("GPTXT,01,01,02,ANTSTATUS=OK"),
        "!AIVDM,1,1,,B,13aGhtw0R<OJf=6LgQ?Ad1FF05`L,0*24",
    ],
)
def test_valid_sentences_of_unused_types_are_counted_as_unknown_not_errors(line):
    fixes, c = decode(line, gga())
    assert len(fixes) == 1
    assert (c.sentences, c.unknown, c.checksum_errors, c.garbled) == (2, 1, 0, 0)


@pytest.mark.parametrize(
    "line",
    [
        pytest.param("$" + GOOD, id="double-dollar"),
        pytest.param(GOOD + "\r\r\n", id="cr-cr-lf"),
        pytest.param("\x00\x00" + GOOD + "\x00", id="nul-padding"),
        pytest.param("  " + GOOD + "\t ", id="whitespace"),
        pytest.param(gga(talker="GN", quality=2).replace("*7A", "*7a"), id="lower-case-hex"),
    ],
)
def test_harmless_framing_is_accepted(line):
    [fix], c = decode(line)
    assert fix.valid and c.checksum_errors == 0 and c.garbled == 0


def test_binary_before_a_sentence_and_collided_sentences_cost_only_the_broken_piece():
    line = b"\xb5b\x01\x07\x00$" + gga().encode() + b"\r\n"
    [fix], c = decode(line)
    assert fix.valid and c.garbled == 1 and c.sentences == 1
    collided = "$GPGGA,030130" + rmc()
    [fix], c = decode(collided)
    assert fix.valid and c.checksum_errors == 1 and c.sentences == 1


def test_comments_and_blank_lines():
    fixes, c = decode("# a comment $GPGGA,1", "", "   ", "(1700000000.0) # receive-time comment", gga())
    assert len(fixes) == 1 and c.comments == 2 and c.lines == 3 and c.fragments == 1


def test_several_lines_in_one_feed():
    fixes, c = decode(f"{gga()}\r\n{rmc()}\n{gga('120001.00')}")
    assert len(fixes) == 2 and c.sentences == 3


# --- property tests -----------------------------------------------------------------------------------

REAL = [
    "$GPGGA,043539.00,4333.190206,N,00127.618380,E,1,05,1.3,250.8,M,50.0,M,,*62",
    "$GNGNS,043539.00,4333.190206,N,00127.618380,E,AAAAN,14,1.3,250.8,50.0,,,V*62",
    "$GPRMC,043539.00,A,4333.190206,N,00127.618380,E,0.0,,040925,1.7,W,A,V*7C",
    "$GPGST,150119.000,004.0,008.7,004.7,132.3,006.8,007.2,00014*71",
    "$GPZDA,130711,01,06,2011,01,00*49",
    "$HEHDT,4.0,T*2B",
    "$GNVTG,,T,,M,0.117,N,0.216,K,A*3F",
    "$GNGSA,A,3,03,19,27,13,,,,,,,,,2.75,2.56,1.00*10",
    "$GPGLL,2638.1727,N,08011.3892,W,030130.000,A,A*4E",
    "(1700000000.5) $GPGGA,012530.562,4131.7353,N,09336.8150,W,1,05,50.,1,M,,M,,*6F",
]


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.binary(max_size=200), st.text(max_size=100)), max_size=20))
def test_arbitrary_bytes_never_crash_and_counters_stay_consistent(chunks):
    dec = NmeaDecoder()
    fixes = [f for chunk in chunks for f in dec.feed(chunk)] + dec.flush()
    assert_consistent(dec.counters)
    assert len(fixes) == dec.counters.fixes
    assert all(f.valid == (f.lat_deg is not None) for f in fixes)


@st.composite
def mutated(draw):
    """A real sentence with a few bytes replaced, inserted or deleted."""
    data = bytearray(draw(st.sampled_from(REAL)).encode())
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(data)))
        op = draw(st.sampled_from(["replace", "insert", "delete"]))
        byte = draw(st.integers(0, 255))
        if op == "insert" or not data or i == len(data):
            data.insert(i, byte)
        elif op == "replace":
            data[i] = byte
        else:
            del data[i]
    return bytes(data)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(mutated(), st.sampled_from(REAL).map(str.encode)), min_size=1, max_size=30))
def test_mutated_real_sentences_never_crash_and_valid_fixes_are_plausible(lines):
    dec = NmeaDecoder(date=DATE)
    fixes = [f for line in lines for f in dec.feed(line)] + dec.flush()
    assert_consistent(dec.counters)
    for f in fixes:
        assert math.isfinite(f.t)
        if f.valid:
            assert -90 <= f.lat_deg <= 90 and -180 <= f.lon_deg <= 180 and f.quality in range(1, 6)
        for v in (f.hdop, f.speed_mps, f.sigma_lat_m, f.sigma_lon_m, f.sigma_alt_m):
            assert v is None or (math.isfinite(v) and v >= 0)
        for v in (f.course_rad, f.heading_rad):
            assert v is None or 0 <= v < 2 * math.pi


# --- file helper and command line ---------------------------------------------------------------------


def test_iter_fixes_reads_a_path_and_reports_a_missing_file(tmp_path):
    path = tmp_path / "drive.nmea"
    path.write_bytes(b"\n".join(x.encode() for x in (gga(), rmc(), gga("120001.00"))))
    fixes = list(iter_fixes(path, NmeaDecoder(date=DATE)))
    assert [f.time_utc.second for f in fixes] == [0, 1]
    with pytest.raises(SourceError, match="cannot read"):
        list(iter_fixes(tmp_path / "missing.nmea"))


def test_cli_on_garbage_prints_no_fix_and_counts_everything(tmp_path, capsys):
    path = tmp_path / "garbage.log"
    path.write_bytes(bytes(range(256)) * 4 + b"\n$GPGGA,bad*00\n" + gga()[:-1].encode() + b"\n")
    assert main(["nmea", str(path)]) == 0
    out, err = capsys.readouterr()
    assert out == ""
    assert "checksum errors: 1" in err and "fixes: 0" in err and "garbled: " in err


def test_cli_date_option_and_error_on_a_missing_file(tmp_path, capsys):
    path = tmp_path / "gga_only.log"
    path.write_text(gga() + "\n")
    assert main(["nmea", "--date", "2024-05-17", str(path)]) == 0
    out, _ = capsys.readouterr()
    assert '"time": "2024-05-17T12:00:00.000Z"' in out
    assert main(["nmea", str(tmp_path / "missing.log")]) == 1
    assert "error:" in capsys.readouterr().err
