"""Tests for fitting, saving and loading calibration curves."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dvr_perception.calibration import (
    CalibrationCurve,
    calibration_stimuli,
    fit_calibration,
    load_calibration,
    measured_transmittance,
    save_calibration,
)
from dvr_perception.errors import DVRInputError
from dvr_perception.measures import calibrate


def test_truthful_ratings_give_identity():
    stims = calibration_stimuli(size=32)
    measured = [measured_transmittance(s) for s in stims]
    rated = [s.transmittance for s in stims]
    curve = fit_calibration(measured, rated)
    grid = np.linspace(0, 1, 101)
    np.testing.assert_allclose(curve(grid), grid, atol=1e-12)
    assert curve.x[0] == 0.0
    assert curve.x[-1] == 1.0


def test_noisy_monotone_ratings():
    rng = np.random.default_rng(1)
    x = np.repeat(np.linspace(0.1, 0.9, 9), 4)  # 4 ratings per stimulus
    truth = x**0.7  # a viewer who sees layers as more transparent
    rated = np.clip(truth + rng.normal(0, 0.02, x.size), 0, 1)
    curve = fit_calibration(x, rated)
    assert np.all(np.diff(curve.y) >= 0)
    means = rated.reshape(9, 4).mean(axis=1)
    # the per-stimulus means are already increasing here, so the fit reproduces them exactly
    assert np.all(np.diff(means) > 0)
    np.testing.assert_allclose(curve(x[::4]), means, atol=1e-12)
    assert np.max(np.abs(curve(x[::4]) - x[::4] ** 0.7)) < 0.03


def test_non_monotone_ratings_give_isotonic_fit():
    curve = fit_calibration([0.1, 0.3, 0.5, 0.7, 0.9], [0.2, 0.6, 0.4, 0.5, 0.8], anchor=False)
    assert curve.x == (0.1, 0.3, 0.5, 0.7, 0.9)
    np.testing.assert_allclose(curve.y, [0.2, 0.5, 0.5, 0.5, 0.8])
    # least squares among monotone fits: beats a hand-made monotone alternative
    rated = np.array([0.2, 0.6, 0.4, 0.5, 0.8])
    assert np.sum((np.array(curve.y) - rated) ** 2) < np.sum(
        (np.array([0.2, 0.45, 0.45, 0.5, 0.8]) - rated) ** 2
    )


def test_ties_are_averaged_and_weighted():
    # x = 0.2 rated 0.9 twice, x = 0.4 rated 0.3 once: pooled (2*0.9 + 0.3)/3 = 0.7
    curve = fit_calibration([0.2, 0.2, 0.4], [0.9, 0.9, 0.3], anchor=False)
    np.testing.assert_allclose(curve.y, [0.7, 0.7])


def test_anchor_and_constant_extrapolation():
    curve = fit_calibration([0.2, 0.8], [0.4, 0.6], anchor=False)
    assert float(curve(0.0)) == pytest.approx(0.4)
    anchored = fit_calibration([0.2, 0.8], [0.4, 0.6])
    assert float(anchored(0.0)) == 0.0
    assert float(anchored(1.0)) == 1.0
    with pytest.raises(DVRInputError, match="distinct"):
        fit_calibration([0.5, 0.5], [0.4, 0.6], anchor=False)


def test_curve_works_with_measures_calibrate():
    curve = CalibrationCurve((0.0, 0.5, 1.0), (0.0, 0.7, 1.0))
    assert float(calibrate(0.25, curve)) == pytest.approx(0.35)
    x, y = curve
    assert x == (0.0, 0.5, 1.0)
    assert y == (0.0, 0.7, 1.0)


@pytest.mark.parametrize(
    ("x", "y", "word"),
    [
        ((0.0, 0.5), (0.5, 0.2), "non-decreasing"),
        ((0.5, 0.2), (0.1, 0.2), "strictly increasing"),
        ((0.0, 1.5), (0.1, 0.2), r"x\[1\]"),
        ((0.0, 1.0), (0.1,), "at least 2"),
    ],
)
def test_curve_validation(x, y, word):
    with pytest.raises(DVRInputError, match=word):
        CalibrationCurve(x, y)


@pytest.mark.parametrize(
    ("measured", "rated", "word"),
    [
        ([0.1, 0.2], [0.1], "same length"),
        ([0.1, 1.2], [0.1, 0.2], "measured"),
        ([0.1, 0.2], [0.1, np.nan], "rated"),
        ([], [], "measured"),
    ],
)
def test_fit_bad_input(measured, rated, word):
    with pytest.raises(DVRInputError, match=word):
        fit_calibration(measured, rated)


def test_round_trip(tmp_path):
    curve = fit_calibration([0.1, 0.3, 0.6], [0.15, 0.35, 0.5])
    path = save_calibration(curve, tmp_path / "viewer.json")
    doc = json.loads(path.read_text())
    assert doc == {"version": 1, "x": list(curve.x), "y": list(curve.y)}
    assert load_calibration(path) == curve
    # a plain pair is accepted too
    save_calibration(([0, 1], [0, 0.9]), tmp_path / "pair.json")
    assert load_calibration(tmp_path / "pair.json").y == (0.0, 0.9)


def _write(tmp_path, doc, name="c.json"):
    p = tmp_path / name
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return p


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        ({"version": 1, "x": [0, 0.5, 1], "y": [0, 0.6, 0.4]}, "'y' must be non-decreasing"),
        ({"version": 1, "x": [0, 0.7, 0.5], "y": [0, 0.2, 0.4]}, "'x' must be strictly"),
        ({"version": 1, "x": [0, 1], "y": [0, 1.2]}, r"'y\[1\]' must lie in \[0, 1\]"),
        ({"version": 1, "x": [0, 1], "y": [0, 0.5, 1]}, "'y' must have as many"),
        ({"version": 1, "x": [0, "a"], "y": [0, 1]}, r"'x\[1\]' must be a finite number"),
        ({"version": 2, "x": [0, 1], "y": [0, 1]}, "'version' must be 1"),
        ({"version": 1, "y": [0, 1]}, "'x' must be a list"),
        ([0, 1], "top level"),
        ("{not json", "not valid JSON"),
    ],
)
def test_load_rejects_bad_files(tmp_path, doc, field):
    p = _write(tmp_path, doc)
    with pytest.raises(DVRInputError, match=field) as info:
        load_calibration(p)
    assert str(p) in str(info.value)


def test_load_missing_file(tmp_path):
    with pytest.raises(DVRInputError, match="not found"):
        load_calibration(tmp_path / "nope.json")


def test_save_is_atomic(tmp_path, monkeypatch):
    target = tmp_path / "c.json"
    target.write_text("old")
    with pytest.raises(DVRInputError):
        save_calibration(([0, 1], [1, 0]), target)
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json"]
