"""The accuracy table of a product against check points (core.accuracy)."""

import numpy as np
import pytest

from recon3d.core.accuracy import AccuracyReport


def test_table_of_known_errors():
    errors = np.array([0.5, -0.5, 1.0, -1.5, 2.5, np.nan, -0.0, 0.25])
    t = AccuracyReport.from_errors(errors, product="DSM", reference="check points")
    e = errors[np.isfinite(errors)]
    assert t.n == 7
    assert t.mean == pytest.approx(2.25 / 7)
    assert t.std == pytest.approx(np.std(e, ddof=1))
    assert t.rms == pytest.approx(np.sqrt(np.mean(e**2)))
    assert t.max_abs == 2.5
    assert t.nmad == pytest.approx(1.4826 * 0.75)  # median 0.25; |e - 0.25| has median 0.75
    assert t.within_1m == pytest.approx(100 * 5 / 7)  # +-1 m counts its ends
    assert t.within_2m == pytest.approx(100 * 6 / 7)
    assert sum(t.histogram["counts"]) == 7


def test_errors_in_feet_are_reported_in_metres():
    t = AccuracyReport.from_errors(np.array([1.0, -3.0, 5.0]), product="DTM", reference="r", metres_per_unit=0.3048)
    assert t.max_abs == pytest.approx(5 * 0.3048)
    assert t.within_1m == pytest.approx(200 / 3)  # 0.30 and 0.91 m in, 1.52 m out


def test_no_finite_error_gives_an_empty_table():
    t = AccuracyReport.from_errors(np.array([np.nan, np.inf]), product="DSM", reference="r")
    assert t.n == 0 and np.isnan(t.rms)
