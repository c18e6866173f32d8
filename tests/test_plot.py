"""``sumhe plot``: replay JSON lines (and a truth) to a PNG; outages from the ``gps`` field; bad input handled."""

import json

import numpy as np
import pytest

from sumhe.cli import main
from sumhe.errors import ConfigError
from sumhe.plot import PlotError, load_track, merge_spans, outage_spans, track_from_records


def test_outage_spans_run_from_the_first_outage_estimate_to_the_next_other_one():
    t = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    gps = ["ok", "outage", "outage", "ok", "rejected", "outage", "ok", "outage"]
    assert outage_spans(t, gps) == [(1.0, 3.0), (5.0, 6.0), (7.0, 7.0)]
    assert outage_spans(t, ["ok"] * 8) == []
    assert merge_spans([(5.0, 6.0), (1.0, 3.0), (2.5, 4.0), (6.0, 6.5)]) == [(1.0, 4.0), (5.0, 6.5)]


def test_records_without_time_or_position_are_left_out_and_the_rest_sorted_by_time():
    records = [
        {"t": 2.0, "lat": 50.0, "lon": 14.0, "gps": "ok", "window": 3, "bound_east": 0.5, "bound_north": 0.7},
        {"t": 1.0, "lat": 50.0, "lon": 14.0, "gps": "outage"},
        {"t": 3.0, "lat": None, "lon": 14.0, "gps": "ok"},
        {"t": "x", "lat": 50.0, "lon": 14.0},
        {"lat": 50.0, "lon": 14.0},
        {"t": True, "lat": 50.0, "lon": 14.0},
    ]
    track = track_from_records(records, "a")
    np.testing.assert_array_equal(track.t, [1.0, 2.0])
    assert list(track.gps) == ["outage", "ok"]
    np.testing.assert_array_equal(track.window, [0.0, 3.0])
    assert np.isnan(track.bound_east[0]) and track.bound_east[1] == 0.5 and track.has_bounds
    with pytest.raises(PlotError, match="no estimates"):
        track_from_records(records[2:], "b")


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_track(tmp_path / "missing.jsonl")
    garbled = tmp_path / "garbled.jsonl"
    garbled.write_text('not json\n[1, 2]\n\n{"t": 5.0, "lat": 50.0, "lon": 14.0, "gps": "ok"}\n')
    track = load_track(garbled)
    assert track.label == "garbled" and len(track.t) == 1
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    with pytest.raises(PlotError):
        load_track(empty, "x")


@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    """A 40 s simulated drive with a 10 s outage replayed by the MHE and the EKF, and a copy of the EKF's output
    with feasible-set bounds added (the MHE reports its own; the EKF none)."""
    d = tmp_path_factory.mktemp("plot")
    assert main(["simulate", "--out", str(d), "--duration", "40", "--outage", "15+10", "--seed", "2"]) == 0
    out = {}
    for name in ("mhe", "ekf"):
        out[name] = d / f"{name}.jsonl"
        argv = ["replay", str(d / "drive.log"), "--nmea", str(d / "drive.nmea"), "--estimator", name]
        assert main([*argv, "--out", str(out[name])]) == 0
    lines = [json.loads(line) for line in out["ekf"].read_text().splitlines()]
    with_bounds = d / "bounded.jsonl"
    with_bounds.write_text(
        "".join(
            json.dumps({**r, "bound_east": 0.5 + 0.1 * i % 3, "bound_north": 0.4}) + "\n" for i, r in enumerate(lines)
        )
    )
    out["bounded"] = with_bounds
    out["truth"] = d / "truth.csv"
    return out


def _image(path):
    image = pytest.importorskip("matplotlib.image", reason="matplotlib (the 'plot' extra) is not installed")
    return image.imread(str(path))


def test_plot_of_replays_with_a_truth_is_a_non_trivial_png(replays, tmp_path, capsys):
    pytest.importorskip("matplotlib", reason="matplotlib (the 'plot' extra) is not installed")
    png = tmp_path / "all.png"
    argv = ["plot", str(replays["mhe"]), str(replays["ekf"]), str(replays["bounded"]), "--truth", str(replays["truth"])]
    assert main([*argv, "--label", "MHE", "--label", "EKF", "--label", "EKF+bounds", "--out", str(png)]) == 0
    assert "MHE, EKF, EKF+bounds" in capsys.readouterr().err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 30_000
    pixels = _image(png)
    assert pixels.shape[:2] == (1040, 1500)  # four time panels: error, window length, eph, bounds
    assert pixels[..., :3].std() > 0.05  # not a blank canvas
    # no truth: the trajectory, the window length, the MHE's eph and bounds (a smaller figure)
    small = tmp_path / "mhe.png"
    assert main(["plot", str(replays["mhe"]), "--out", str(small)]) == 0
    assert _image(small).shape[:2] == (780, 1500)
    # the EKF: no window, no bounds; its eph only
    ekf = tmp_path / "ekf.png"
    assert main(["plot", str(replays["ekf"]), "--out", str(ekf)]) == 0
    assert _image(ekf).shape[:2] == (700, 1500)


def test_plot_input_errors_exit_with_a_message(replays, tmp_path, capsys):
    png = tmp_path / "x.png"
    assert main(["plot", str(replays["mhe"]), "--label", "a", "--label", "b", "--out", str(png)]) == 1
    assert "2 labels for 1 files" in capsys.readouterr().err
    bad_truth = tmp_path / "truth.csv"
    bad_truth.write_text("t,lat\n1,2\n")
    assert main(["plot", str(replays["mhe"]), "--truth", str(bad_truth), "--out", str(png)]) == 1
    assert "missing truth columns" in capsys.readouterr().err
    assert main(["plot", str(tmp_path / "nothing.jsonl"), "--out", str(png)]) == 1
    assert "cannot read" in capsys.readouterr().err
    assert not png.exists()


def test_the_demo_figure_zooms_on_each_outage_and_plots_raw_gnss_errors(replays, tmp_path):
    pytest.importorskip("matplotlib", reason="matplotlib (the 'plot' extra) is not installed")
    from sumhe.bench.demo import gnss_records
    from sumhe.plot import plot_outages
    from sumhe.sim import load_truth

    truth = load_truth(replays["truth"])
    tracks = [load_track(replays["mhe"], "sumhe"), load_track(replays["ekf"], "ekf")]
    fixes = track_from_records(gnss_records(replays["truth"].with_name("drive.nmea")), "raw GNSS")
    assert len(fixes.t) > 200 and not np.any((fixes.t > truth.t[0] + 15.5) & (fixes.t < truth.t[0] + 24.5))
    png = plot_outages(tracks, truth, [(truth.t[0] + 15.0, truth.t[0] + 25.0)], tmp_path / "demo.png", fixes)
    fig = _image(png)
    assert fig.shape[:2] == (950, 1000)  # overview + one zoomed outage above, errors over time below
    zoom = fig[: fig.shape[0] // 2, fig.shape[1] // 2 :, :3]
    assert zoom.std() > 0.05, "the zoomed panel shows the tracks"
