"""Figures of replays (``sumhe plot``): the JSON lines of ``sumhe replay ... --out est.jsonl``, one file per
estimator, and optionally the drive's ``truth.csv``.

One PNG: the trajectory (every estimator overlaid, the truth in black, the stretches without GPS shaded), and
against time the error to the truth, the estimator's window length, its error estimate (``eph``, 95 %: with the
error to the truth beside it when there is one) and the half-widths of its feasible set (``bound_east``/
``bound_north``) where the JSON has them. Outages are the runs of estimates with ``gps`` =
``"outage"``. matplotlib is the optional extra ``plot`` (``pip install 'sumhe[plot]'``), imported only when a
figure is drawn; everything else here works without it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sumhe.bench import metrics
from sumhe.errors import ConfigError, SumheError
from sumhe.geo import LocalFrame
from sumhe.sim import Truth

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
OUTAGE_COLOUR = "orange"
MATPLOTLIB_MISSING = "matplotlib is not installed: no plot (pip install 'sumhe[plot]')"


class PlotError(SumheError):
    """A figure cannot be drawn (no matplotlib, no usable estimates)."""


@dataclass(frozen=True, eq=False)
class Track:
    """One estimator's replay, in time order: ``t`` (s), WGS84 ``lat``/``lon`` (deg), ``gps`` status, ``window``
    length (steps; 0 where the estimator has none), ``bound_east``/``bound_north`` and ``eph`` (m; NaN where
    absent)."""

    label: str
    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    gps: NDArray[np.str_]
    window: FloatArray
    bound_east: FloatArray
    bound_north: FloatArray
    eph: FloatArray

    @property
    def has_bounds(self) -> bool:
        return bool(np.any(np.isfinite(self.bound_east)))

    @property
    def has_eph(self) -> bool:
        return bool(np.any(np.isfinite(self.eph)))


def _number(value: Any) -> float:
    """A JSON number as float; NaN for null, absent or not a number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return math.nan
    return float(value)


def track_from_records(records: Iterable[dict[str, Any]], label: str) -> Track:
    """A :class:`Track` of JSON estimates; records without a finite ``t``/``lat``/``lon`` are left out (counted in
    the log). PlotError when none is usable."""
    rows = []
    skipped = 0
    for r in records:
        t, lat, lon = _number(r.get("t")), _number(r.get("lat")), _number(r.get("lon"))
        if not (math.isfinite(t) and math.isfinite(lat) and math.isfinite(lon)):
            skipped += 1
            continue
        window = _number(r.get("window"))
        rows.append(
            (
                t,
                lat,
                lon,
                str(r.get("gps", "")),
                window if math.isfinite(window) else 0.0,
                _number(r.get("bound_east")),
                _number(r.get("bound_north")),
                _number(r.get("eph")),
            )
        )
    if skipped:
        log.warning("%s: %d estimates without a time or position left out", label, skipped)
    if not rows:
        raise PlotError(f"{label}: no estimates with a time and a position")
    rows.sort(key=lambda row: row[0])
    t, lat, lon, gps, window, be, bn, eph = zip(*rows, strict=True)
    return Track(
        label,
        *(np.array(v, dtype=float) for v in (t, lat, lon)),
        np.array(gps),
        *map(np.array, (window, be, bn, eph)),
    )


def load_track(path: str | Path, label: str | None = None) -> Track:
    """The JSON lines of one replay (named ``label``, else the file's stem). Lines that are not JSON objects are
    skipped (counted in the log); ConfigError when the file cannot be read, PlotError when nothing is usable."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{p}: cannot read: {e}") from e
    records = []
    bad = 0
    for line in lines:
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            bad += 1
            continue
        if isinstance(record, dict):
            records.append(record)
        else:
            bad += 1
    if bad:
        log.warning("%s: %d lines that are not JSON objects skipped", p, bad)
    return track_from_records(records, label or p.stem)


def outage_spans(t: Sequence[float] | FloatArray, gps: Sequence[str] | NDArray[np.str_]) -> list[tuple[float, float]]:
    """The stretches (s) of consecutive estimates with ``gps == "outage"``: from the first such estimate to the next
    estimate with another status (or the last outage estimate at the end)."""
    tt = np.asarray(t, dtype=float)
    out = np.asarray(gps) == "outage"
    spans = []
    k = 0
    while k < len(tt):
        if not out[k]:
            k += 1
            continue
        j = k
        while j + 1 < len(tt) and out[j + 1]:
            j += 1
        spans.append((float(tt[k]), float(tt[j + 1] if j + 1 < len(tt) else tt[j])))
        k = j + 1
    return spans


def merge_spans(spans: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
    """Overlapping or touching spans joined, in time order."""
    merged: list[tuple[float, float]] = []
    for start, end in sorted(spans):
        if merged and start <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], end))
        else:
            merged.append((start, end))
    return merged


def truth_in_frame(truth: Truth, frame: LocalFrame) -> Truth:
    """The truth with its east/north recomputed from its latitude/longitude in ``frame``."""
    enu = frame.to_enu(truth.lat, truth.lon, frame.alt0_m)
    return dataclasses.replace(truth, east=enu[:, 0], north=enu[:, 1])


def track_errors(track: Track, truth: Truth, frame: LocalFrame) -> tuple[FloatArray, FloatArray]:
    """Times (s) and horizontal errors (m) of the track's estimates within the truth's time span."""
    inside = (track.t >= truth.t[0]) & (track.t <= truth.t[-1])
    t = track.t[inside]
    return t, metrics.geodetic_errors(t, track.lat[inside], track.lon[inside], truth, frame)


def plot_replays(tracks: Sequence[Track], out: str | Path, truth: Truth | None = None, title: str = "") -> Path:
    """Draw the figure of the module docstring into the PNG ``out``; PlotError without matplotlib or tracks."""
    if not tracks:
        raise PlotError("nothing to plot: no replays given")
    try:
        from matplotlib.figure import Figure
    except ImportError as e:
        raise PlotError(MATPLOTLIB_MISSING) from e
    frame = LocalFrame(float(tracks[0].lat[0]), float(tracks[0].lon[0]))
    local_truth = truth_in_frame(truth, frame) if truth is not None else None
    spans = merge_spans(s for tr in tracks for s in outage_spans(tr.t, tr.gps))
    t0 = min(float(tr.t[0]) for tr in tracks)
    panels = [name for name, show in _time_panels(tracks, local_truth) if show]
    fig = Figure(figsize=(15, max(7.0, 2.6 * len(panels))), layout="constrained")
    grid = fig.add_gridspec(max(len(panels), 1), 2, width_ratios=(1.0, 1.4))
    ax_map = fig.add_subplot(grid[:, 0])
    _draw_map(ax_map, tracks, local_truth, frame, spans)
    ax_map.set_title(title or "trajectory (GPS outages shaded)")
    axes: list[Any] = []
    for row, name in enumerate(panels):
        ax = fig.add_subplot(grid[row, 1], sharex=axes[0] if axes else None)
        axes.append(ax)
        for start, end in spans:
            ax.axvspan(start - t0, end - t0, color=OUTAGE_COLOUR, alpha=0.25, lw=0)
        _draw_panel(ax, name, tracks, local_truth, frame, t0)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    if axes:
        axes[-1].set_xlabel("time (s) from the first estimate")
    path = Path(out)
    fig.savefig(path, dpi=100)
    return path


def _time_panels(tracks: Sequence[Track], truth: Truth | None) -> list[tuple[str, bool]]:
    return [
        ("error", truth is not None),
        ("window", any(np.any(tr.window > 0) for tr in tracks)),
        ("eph", any(tr.has_eph for tr in tracks)),
        ("bounds", any(tr.has_bounds for tr in tracks)),
    ]


def _draw_map(
    ax: Any, tracks: Sequence[Track], truth: Truth | None, frame: LocalFrame, spans: list[tuple[float, float]]
) -> None:
    if truth is not None:
        ax.plot(truth.east, truth.north, color="black", lw=1.0, label="truth")
    for i, tr in enumerate(tracks):
        enu = frame.to_enu(tr.lat, tr.lon, frame.alt0_m)
        ax.plot(enu[:, 0], enu[:, 1], lw=0.8, color=_colour(i), label=tr.label)
    ref = tracks[0]
    ref_enu = frame.to_enu(ref.lat, ref.lon, frame.alt0_m)
    for start, end in spans:
        if truth is not None:
            sel = (truth.t >= start) & (truth.t <= end)
            east, north = truth.east[sel], truth.north[sel]
        else:
            sel = (ref.t >= start) & (ref.t <= end)
            east, north = ref_enu[sel, 0], ref_enu[sel, 1]
        ax.plot(east, north, color=OUTAGE_COLOUR, lw=7, alpha=0.35, solid_capstyle="butt")
    ax.plot([], [], color=OUTAGE_COLOUR, lw=7, alpha=0.35, label="GPS outage")
    ax.set(xlabel="east (m)", ylabel="north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)


def _draw_panel(ax: Any, name: str, tracks: Sequence[Track], truth: Truth | None, frame: LocalFrame, t0: float) -> None:
    if name == "error":
        assert truth is not None
        for i, tr in enumerate(tracks):
            t, err = track_errors(tr, truth, frame)
            ax.plot(t - t0, err, lw=0.8, color=_colour(i), label=tr.label)
        ax.set(ylabel="horizontal error (m)", title="error against the truth")
    elif name == "window":
        for i, tr in enumerate(tracks):
            if np.any(tr.window > 0):
                ax.step(tr.t - t0, tr.window, where="post", lw=0.8, color=_colour(i), label=tr.label)
        ax.set(ylabel="window (steps)", title="estimator window length")
    elif name == "eph":
        for i, tr in enumerate(tracks):
            if tr.has_eph:
                ax.plot(tr.t - t0, tr.eph, lw=0.8, color=_colour(i), label=f"{tr.label} eph")
                if truth is not None:
                    t, err = track_errors(tr, truth, frame)
                    ax.plot(t - t0, err, lw=0.6, ls=":", color=_colour(i), label=f"{tr.label} error")
        ax.set(ylabel="m", title="error estimate eph (95 %) and the error")
    else:
        for i, tr in enumerate(tracks):
            if tr.has_bounds:
                ax.plot(tr.t - t0, tr.bound_east, lw=0.8, color=_colour(i), label=f"{tr.label} east")
                ax.plot(tr.t - t0, tr.bound_north, lw=0.8, ls="--", color=_colour(i), label=f"{tr.label} north")
        ax.set(ylabel="half-width (m)", title="feasible-set bounds of the newest position")


def _colour(index: int) -> str:
    """The same colour for an estimator in every panel (matplotlib's default cycle)."""
    return f"C{index % 10}"


ZOOM_MARGIN_S = 3.0
"""Time before and after an outage drawn in its zoomed map (s)."""
ZOOM_PAD_M = 3.0
"""Space around the largest error in a zoomed map (m)."""


def plot_outages(
    tracks: Sequence[Track],
    truth: Truth,
    outages: Sequence[tuple[float, float]],
    out: str | Path,
    fixes: Track | None = None,
    title: str = "",
) -> Path:
    """The demo's figure: an overview map; for each outage (``(start, end)``, s on the tracks' clock) a map zoomed
    on the true position where GPS returns, the truth, the raw GNSS ``fixes`` and every track drawn through it, so
    the gap each estimator built up is seen at metre scale; below, the horizontal error against the truth over
    time of the fixes and of each track (log scale, outages shaded). PlotError without matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError as e:
        raise PlotError(MATPLOTLIB_MISSING) from e
    frame = LocalFrame(float(truth.lat[0]), float(truth.lon[0]))
    local_truth = truth_in_frame(truth, frame)
    shown = ([fixes] if fixes is not None else []) + list(tracks)
    styles = {id(tr): _style(tr, i, raw=False) for i, tr in enumerate(tracks)}
    if fixes is not None:
        styles[id(fixes)] = _style(fixes, 0, raw=True)
    fig = Figure(figsize=(5.0 * (1 + len(outages)), 9.5), layout="constrained")
    grid = fig.add_gridspec(2, 1 + len(outages), height_ratios=(1.3, 1.0))
    overview = fig.add_subplot(grid[0, 0])
    _draw_map(overview, tracks, local_truth, frame, list(outages))
    overview.set_title(title or "trajectory (GPS outages shaded)")
    t0 = float(truth.t[0])
    for k, (start, end) in enumerate(outages):
        ax = fig.add_subplot(grid[0, 1 + k])
        _draw_zoom(ax, shown, styles, local_truth, frame, (start - ZOOM_MARGIN_S, end + ZOOM_MARGIN_S), end)
        ax.set_title(f"outage {k + 1} ({end - start:.0f} s from {start - t0:.0f} s): where GPS returns")
    ax_err = fig.add_subplot(grid[1, :])
    for start, end in outages:
        ax_err.axvspan(start - t0, end - t0, color=OUTAGE_COLOUR, alpha=0.25, lw=0)
    for tr in shown:
        t, err = track_errors(tr, local_truth, frame)
        ax_err.plot(t - t0, np.maximum(err, 1e-3), **styles[id(tr)])
    ax_err.set_yscale("log")
    ax_err.set(
        xlabel="time (s) from the truth's start",
        ylabel="horizontal error (m)",
        title="error against the truth (outages shaded)",
    )
    ax_err.grid(alpha=0.3, which="both")
    ax_err.legend(loc="upper left", fontsize=8)
    path = Path(out)
    fig.savefig(path, dpi=100)
    return path


def _style(track: Track, index: int, raw: bool) -> dict[str, Any]:
    """Raw fixes as grey dots; estimators as lines in their colour (as in :func:`plot_replays`), the first (ours)
    drawn on top, the others beneath the fixes (a peer that follows the fixes would hide them)."""
    if raw:
        return {"ls": "none", "marker": ".", "ms": 3.0, "color": "0.35", "label": track.label, "zorder": 3}
    first = index == 0
    return {"lw": 1.5 if first else 0.8, "color": _colour(index), "label": track.label, "zorder": 4 if first else 2}


def _draw_zoom(
    ax: Any,
    shown: Sequence[Track],
    styles: dict[int, dict[str, Any]],
    truth: Truth,
    frame: LocalFrame,
    span: tuple[float, float],
    at: float,
) -> None:
    """The tracks over ``span`` (s) in a square around the true position at ``at``, wide enough for the largest
    error at that time."""
    sel = (truth.t >= span[0]) & (truth.t <= span[1])
    ax.plot(truth.east[sel], truth.north[sel], color="black", lw=1.2, label="truth")
    k = int(np.clip(np.searchsorted(truth.t, at), 0, len(truth.t) - 1))
    centre = (float(truth.east[k]), float(truth.north[k]))
    half = ZOOM_PAD_M
    for tr in shown:
        inside = (tr.t >= span[0]) & (tr.t <= span[1])
        enu = frame.to_enu(tr.lat[inside], tr.lon[inside], frame.alt0_m)
        ax.plot(enu[:, 0], enu[:, 1], **styles[id(tr)])
        near = np.abs(tr.t[inside] - at) <= 0.5
        if np.any(near):
            gap = np.hypot(enu[near, 0] - centre[0], enu[near, 1] - centre[1])
            half = max(half, float(gap.max()) * 1.2 + ZOOM_PAD_M)
    ax.plot(*centre, marker="x", ms=9, color="black", ls="none", label="truth when GPS returns")
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half))
    ax.set(xlabel="east (m)", ylabel="north (m)")
    ax.set_aspect("equal", adjustable="box")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=7)
