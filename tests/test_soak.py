"""Soak: random LiDAR surveys end to end through the command line (``scripts/soak.py``
runs 50 or more; the suite a few, chosen to cover a refusal of each kind and a
publication). Each either publishes every product or is refused with one line
naming the file, and never leaves a traceback or a work folder behind."""

import importlib.util
from pathlib import Path

import pytest

_SPEC = importlib.util.spec_from_file_location("soak", Path(__file__).resolve().parents[1] / "scripts" / "soak.py")
soak = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(soak)


@pytest.mark.parametrize("seed, damage", [
    (5, None),  # flat-roofed survey, no trees: published
    (4, "flipped"),  # bytes of the header flipped, scale changed by 0.01 %: still a survey, published
    (6, "few_points"),  # cut to 48 points: refused
    (9, "flipped"),  # the CRS record destroyed: refused, asking for --crs
])
def test_random_survey_end_to_end(tmp_path, seed, damage):
    case = soak.make_case(seed, tmp_path / "in")
    assert case["damage"] == damage
    (tmp_path / "work").mkdir()
    row = soak.run_case(case, tmp_path / "work" / "out")
    assert row["problems"] == []
    if row["exit"] == 0:
        assert row["dtm_rms"] < 0.1  # ground check points of the truth terrain
        assert row["buildings"] == row["true_buildings"]
    else:
        assert damage is not None
