"""``sumhe bench mhe`` on a tiny configuration: its parts run and print their figures (correctness, not speed)."""

from __future__ import annotations

import re

import pytest

from sumhe.bench.mhe import MheBenchSettings
from sumhe.bench.mhe_report import run_benchmark


def test_the_accuracy_part_compares_with_the_ekf_raw_and_net_of_the_gnss_offset() -> None:
    bs = MheBenchSettings(
        scenarios=("urban",),
        seeds=(21,),
        gps_errors=("walk",),
        outage_lengths_s=(5.0,),
        duration_s=80.0,
        baselines=("ekf",),
        parts=("accuracy",),
    )
    progress: list[str] = []
    text = "\n".join(run_benchmark(bs, progress.append))
    assert "latency" not in text and "replay" not in text
    means = [float(m) for m in re.findall(r"mhe\s+mean\s+([\d.]+)", text)]
    ratios = re.findall(r"mhe / ekf: mean ([\d.]+)x", text)
    assert len(means) == 2 and len(ratios) == 2  # raw, and net of the offset
    assert 0.0 < means[1] < means[0]  # with walk errors the offset is most of the error
    assert "after the outage" in text  # the smoothed window against the batch estimate
    assert any("outages 5 s" in p for p in progress)


def test_unknown_parts_are_refused() -> None:
    with pytest.raises(ValueError, match="parts"):
        MheBenchSettings(parts=("latency", "speed"))
    with pytest.raises(ValueError, match="parts"):
        MheBenchSettings(parts=())
