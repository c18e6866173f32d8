"""Output destinations (issue 15, item 5): IP addresses or host names, this host only unless
``output.allow_remote = true``; errors name the key. Nothing here sends a datagram anywhere but loopback, and no name
is looked up in the DNS (a name that cannot be encoded fails before any lookup)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from sumhe.config import load_config
from sumhe.errors import ConfigError
from sumhe.io.udp import UdpSender, UdpSink


@pytest.mark.parametrize(
    "dest, why",
    [
        ("http://x:1", "'http://x' is neither an IP address nor a host name"),
        ("under_score:5005", "'under_score' is neither"),
        ("1.2.3.999:5005", "'1.2.3.999' is neither"),
        ("-x.example:5005", "'-x.example' is neither"),
        ("127.0.0.1:0", "is not a host:port destination"),
    ],
)
def test_a_destination_that_is_no_address_or_name_stops_the_config_naming_the_key(dest, why):
    with pytest.raises(ConfigError, match=r"output\.json: ") as e:
        load_config(None, env={"SUMHE_OUTPUT__JSON": f'["{dest}"]'})
    assert why in str(e.value) and "environment variable SUMHE_OUTPUT__JSON" in str(e.value)
    with pytest.raises(ConfigError, match=r"output\.status_udp: "):
        load_config(None, env={"SUMHE_OUTPUT__STATUS_UDP": dest})


@pytest.mark.parametrize("dest", ["127.0.0.1:5005", "localhost:5005", "[::1]:5005", "[ff11::1]:5005", "[ff01::2]:5"])
def test_this_host_is_allowed(dest):
    if ":" in dest.rpartition(":")[0] and not socket.has_ipv6:
        pytest.skip("no IPv6")
    UdpSender([dest], "output.json").close()


def own_address() -> str | None:
    """A non-loopback address of this host, if it has one."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect(("192.0.2.1", 9))  # connecting a UDP socket sends nothing: it only picks the route's source
        addr = s.getsockname()[0]
    return None if addr.startswith("127.") else addr


def test_an_address_of_this_host_is_allowed():
    try:
        addr = own_address()
    except OSError:
        addr = None
    if addr is None:
        pytest.skip("this host has no route off loopback")
    UdpSender([f"{addr}:5005"], "output.json").close()


@pytest.mark.parametrize(
    "dest, what",
    [
        ("255.255.255.255:5005", "broadcast"),
        ("192.0.2.1:5005", "another host"),
        ("[2001:db8::1]:5005", "another host"),
        ("224.0.0.1:5005", "a multicast group reaching beyond this host"),
        ("[ff02::1]:5005", "a multicast group reaching beyond this host"),
        ("0.0.0.0:5005", "the unspecified address"),
    ],
)
def test_broadcast_multicast_and_other_hosts_need_allow_remote(dest, what):
    with pytest.raises(ConfigError, match=r"c\.toml: output\.nmea: ") as e:
        UdpSender([dest], "output.nmea", "c.toml")
    assert f"is {what}, not this host: set output.allow_remote = true" in str(e.value)
    UdpSender([dest], "output.nmea", "c.toml", allow_remote=True).close()  # built, nothing sent


def test_the_sink_reads_allow_remote_from_the_output_settings():
    config = load_config(None, env={"SUMHE_OUTPUT__JSON": '["192.0.2.1:5005"]'})
    with pytest.raises(ConfigError, match=r"output\.json: 192\.0\.2\.1:5005 .* another host"):
        UdpSink(config.output)
    remote = load_config(None, env={"SUMHE_OUTPUT__JSON": '["192.0.2.1:5005"]', "SUMHE_OUTPUT__ALLOW_REMOTE": "true"})
    UdpSink(remote.output).close()


def test_a_name_that_cannot_be_looked_up_is_an_error_naming_the_key():
    with pytest.raises(ConfigError, match=r"c.toml: output.json: cannot resolve 'a{64}'"):
        UdpSender([f"{'a' * 64}:5005"], "output.json", "c.toml")


def test_the_daemon_refuses_a_broadcast_destination_at_start_naming_file_and_key(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text(
        '[can]\ninterface = "virtual"\nchannel = "sumhe-dest-test"\n[can.signals]\n'
        'speed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\nyaw_rate = "ESP_YAW_RATE.YAW_RATE"\n'
        f'[gps]\nport = "{tmp_path / "gps"}"\n[output]\njson = ["255.255.255.255:5005"]\n'
    )
    result = subprocess.run(
        [sys.executable, "-m", "sumhe", "run", "--config", str(config)],
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert f"error: {config}: output.json: 255.255.255.255:5005 (255.255.255.255) is broadcast" in result.stderr
