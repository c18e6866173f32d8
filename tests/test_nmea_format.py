"""The NMEA formatter: checksums, field layout (parsed back by pynmea2 and by sumhe's decoder), rounding, bad input."""

from __future__ import annotations

import math

import pynmea2
import pytest

from sumhe.io.nmea_format import (
    format_gga,
    format_gst,
    format_hdt,
    format_rmc,
    nmea_checksum,
    quantize_angle_rad,
    quantize_latlon,
    sentence,
)

T = 1780300800.0 + 8 * 3600 + 12 * 60 + 34.56  # 2026-06-01 16:12:34.56 UTC


def test_checksum_of_the_classic_example() -> None:
    body = "GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"
    assert nmea_checksum(body) == "47"
    assert sentence(body) == f"${body}*47"


@pytest.mark.parametrize("body", ["GPGGA,1*2", "GP$GGA", "GPGGA\r\n", "GPGGA,é"])
def test_sentence_rejects_bodies_that_would_break_framing(body: str) -> None:
    with pytest.raises(ValueError, match="body"):
        sentence(body)


def test_gga_parses_back_with_pynmea2() -> None:
    line = format_gga(
        T, 50.0755123456, 14.4378987654, 4, sats=12, hdop=0.8, alt_msl_m=205.123, geoid_sep_m=45.0, dgps_age_s=1.0,
        dgps_station="0001",
    )  # fmt: skip
    msg = pynmea2.parse(line, check=True)
    assert line.startswith("$GPGGA,161234.56,5004.")
    assert msg.timestamp.isoformat() == "16:12:34.560000+00:00"
    assert msg.latitude == pytest.approx(50.0755123456, abs=2e-9)
    assert msg.longitude == pytest.approx(14.4378987654, abs=2e-9)
    assert (msg.gps_qual, msg.num_sats, msg.horizontal_dil) == (4, "12", "0.80")
    assert msg.altitude == pytest.approx(205.123)
    assert (msg.geo_sep, msg.age_gps_data, msg.ref_station_id) == ("45.000", "1.0", "0001")
    assert len(line.split(",")) == 15


def test_latitude_keeps_millimetres() -> None:
    lat = 50.0755123456
    fields = format_gga(T, lat, 14.0, 1).split(",")
    assert fields[2] == "5004.5307407"  # 7 decimals of minutes: 1.85e-4 m
    assert abs(quantize_latlon(lat) - lat) * 111_320 < 1e-3


@pytest.mark.parametrize(
    ("lat", "lon", "lat_field", "ns", "lon_field", "ew"),
    [
        (-33.5, -70.25, "3330.0000000", "S", "07015.0000000", "W"),
        (45.877591500, 170.500124833, "4552.6554900", "N", "17030.0074900", "E"),
        (-0.00000000001, -0.00000000001, "0000.0000000", "N", "00000.0000000", "E"),
    ],
)
def test_hemispheres(lat: float, lon: float, lat_field: str, ns: str, lon_field: str, ew: str) -> None:
    line = format_rmc(T, lat, lon, speed_mps=0.0)
    fields = line.split(",")
    assert fields[3:7] == [lat_field, ns, lon_field, ew]
    msg = pynmea2.parse(line, check=True)
    assert msg.latitude == pytest.approx(lat, abs=1e-8)
    assert msg.longitude == pytest.approx(lon, abs=1e-8)


def test_minutes_round_up_into_the_next_degree() -> None:
    lat = 50.0 + 59.99999999 / 60.0  # 59.99999999' rounds to 60.0000000' = the next degree
    lon = -(14.0 + 59.999999996 / 60.0)
    fields = format_gga(T, lat, lon, 1).split(",")
    assert fields[2:6] == ["5100.0000000", "N", "01500.0000000", "W"]
    assert quantize_latlon(lat) == 51.0
    assert quantize_latlon(lon) == -15.0


def test_time_rounds_into_the_next_day_and_date() -> None:
    t = 1780358399.996  # 2026-06-01 23:59:59.996 -> 00:00:00.00 on 2026-06-02
    fields = format_rmc(t, 50.0, 14.0).split(",")
    assert fields[1] == "000000.00"
    assert fields[9] == "020626"


def test_rmc_status_mode_speed_course() -> None:
    line = format_rmc(T, 50.0, 14.0, status="A", mode="E", speed_mps=10.0, course_rad=math.radians(359.9996))
    msg = pynmea2.parse(line, check=True)
    assert (msg.status, msg.mode_indicator) == ("A", "E")
    assert msg.spd_over_grnd == pytest.approx(10.0 * 3600 / 1852, abs=5e-4)
    assert msg.true_course == 0.0  # 359.9996 rounds to 360.000 = 0.000
    assert msg.datestamp.isoformat() == "2026-06-01"
    assert quantize_angle_rad(math.radians(359.9996)) == 0.0


def test_no_fix_sentences_have_empty_fields() -> None:
    gga = format_gga(T, None, None, 0, sats=0, hdop=99.99)
    rmc = format_rmc(T, None, None, status="V", mode="N")
    assert gga.split(",")[2:7] == ["", "", "", "", "0"]
    assert rmc.split(",")[2:9] == ["V", "", "", "", "", "", ""]
    assert pynmea2.parse(gga, check=True).gps_qual == 0
    assert pynmea2.parse(rmc, check=True).status == "V"


def test_dead_reckoning_output_decodes_as_not_a_gnss_fix() -> None:
    """What the service sends while dead reckoning: GGA quality 6, RMC mode E; sumhe's decoder must not take it
    for a measured position."""
    nmea = pytest.importorskip("sumhe.io.nmea")
    lines = [format_gga(T, 50.1, 14.4, 6, sats=0, hdop=99.0), format_rmc(T, 50.1, 14.4, mode="E", speed_mps=3.0)]
    fixes = list(nmea.iter_fixes(lines))
    assert len(fixes) == 1
    assert fixes[0].quality == 6
    assert not fixes[0].valid


def test_gst_and_hdt_parse_back() -> None:
    gst = format_gst(
        T, rms_m=0.5, sigma_lat_m=0.017, sigma_lon_m=0.018, sigma_alt_m=0.03, sigma_major_m=0.02, sigma_minor_m=0.01,
        orientation_rad=math.radians(45.0), talker="GN",
    )  # fmt: skip
    msg = pynmea2.parse(gst, check=True)
    assert gst.startswith("$GNGST,161234.56,")
    assert (msg.rms, msg.std_dev_major, msg.std_dev_minor, msg.orientation) == (0.5, 0.02, 0.01, 45.0)
    assert (msg.std_dev_latitude, msg.std_dev_longitude, msg.std_dev_altitude) == (0.017, 0.018, 0.03)
    hdt = format_hdt(math.radians(-90.0))
    assert hdt == "$GPHDT,270.000,T*" + nmea_checksum("GPHDT,270.000,T")
    assert float(pynmea2.parse(hdt, check=True).heading) == 270.0
    assert format_hdt(None).startswith("$GPHDT,,T*")
    assert format_gst(T, rms_m=None, sigma_lat_m=None, sigma_lon_m=None).startswith("$GPGST,161234.56,,,,,,,*")


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda: format_gga(T, 50.0, 14.0, 9), "quality"),
        (lambda: format_gga(T, 50.0, 14.0, True), "quality"),  # type: ignore[arg-type]
        (lambda: format_gga(T, 50.0, 14.0, 1, sats=100), "sats"),
        (lambda: format_gga(T, 50.0, 14.0, 1, dgps_station="12345"), "dgps_station"),
        (lambda: format_gga(T, 91.0, 14.0, 1), "lat_deg"),
        (lambda: format_gga(T, math.nan, 14.0, 1), "lat_deg"),
        (lambda: format_gga(T, 50.0, 180.5, 1), "lon_deg"),
        (lambda: format_gga(T, 50.0, None, 1), "lat_deg"),
        (lambda: format_gga(T, 50.0, 14.0, 1, hdop=math.inf), "hdop"),
        (lambda: format_gga(T, 50.0, 14.0, 1, decimals=0), "decimals"),
        (lambda: format_gga(math.nan, 50.0, 14.0, 1), "t_unix_s"),
        (lambda: format_gga(-1.0, 50.0, 14.0, 1), "t_unix_s"),
        (lambda: format_rmc(T, 50.0, 14.0, status="X"), "status"),
        (lambda: format_rmc(T, 50.0, 14.0, mode="Z"), "mode"),
        (lambda: format_rmc(T, 50.0, 14.0, mode="AD"), "mode"),
        (lambda: format_rmc(T, 50.0, 14.0, speed_mps=-1.0), "speed_mps"),
        (lambda: format_rmc(T, 50.0, 14.0, course_rad=math.nan), "course_rad"),
        (lambda: format_rmc(T, 50.0, 14.0, talker="gp"), "talker"),
        (lambda: format_rmc(T, 50.0, 14.0, talker="GPS"), "talker"),
        (lambda: format_gst(T, rms_m=1.0, sigma_lat_m=-1.0, sigma_lon_m=1.0), "sigma_lat_m"),
        (lambda: format_hdt(math.inf), "heading_rad"),
    ],
)
def test_bad_values_raise_naming_the_argument(call: object, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        call()  # type: ignore[operator]
