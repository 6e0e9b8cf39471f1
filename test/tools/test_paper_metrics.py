"""Fig. 2's transient metrics, the |mean error| noise floor, and the committed report figures."""

import math
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.optimize

from snn_tools.experiments.paper_metrics import noise_floor, transient_metrics

RESULTS = Path(__file__).resolve().parents[2] / 'results'


def test_transient_metrics_of_a_damped_oscillation_match_its_closed_form():
    """e(t) = 2 e^-t cos 2t with sigma = 0.1: enters 3 sigma where 2 e^-t cos 2t = 0.3, crosses
    zero at pi/4, swings to its extremum at tan 2t = -1/2, settles (|e| < 0.1 for good) where
    the last lobe's peak falls below 0.1."""
    t = np.linspace(0.0, 10.0, 200_001)
    e = 2.0 * np.exp(-t) * np.cos(2.0 * t)
    m = transient_metrics(t, e, np.full_like(t, 0.1))
    enter = scipy.optimize.brentq(lambda s: 2 * math.exp(-s) * math.cos(2 * s) - 0.3, 0.0, math.pi / 4)
    assert m['enter_3sigma_s'] == pytest.approx(enter, abs=1e-4)
    assert m['zero_crossing_s'] == pytest.approx(math.pi / 4, abs=1e-4)
    extremum = (math.pi - math.atan(0.5)) / 2
    assert m['overshoot'] == pytest.approx(2 * math.exp(-extremum) * abs(math.cos(2 * extremum)), rel=1e-6)
    # settling: the last time |e| = 0.1 (on the last lobe whose peak exceeds 0.1)
    peaks = [(k * math.pi - math.atan(0.5)) / 2 for k in range(1, 6)]
    last = max(p for p in peaks if 2 * math.exp(-p) * abs(math.cos(2 * p)) > 0.1)
    next_zero = last + (math.pi / 2 + math.atan(0.5)) / 2
    settle = scipy.optimize.brentq(lambda s: 2 * math.exp(-s) * abs(math.cos(2 * s)) - 0.1, last, next_zero)
    assert m['settle_s'] == pytest.approx(settle, abs=1e-4)


def test_the_overshoot_is_the_first_swing_past_zero_not_a_later_one():
    """e = (1 + t) cos t grows: the overshoot is the extremum between the first two zero
    crossings (pi/2, 3 pi/2), where tan t = 1 / (1 + t), not the larger later swings."""
    t = np.linspace(0.0, 12.0, 240_001)
    m = transient_metrics(t, (1 + t) * np.cos(t), None)
    extremum = scipy.optimize.brentq(lambda s: -math.sin(s) * (1 + s) + math.cos(s), math.pi / 2 + 1e-9,
                                     1.5 * math.pi - 1e-9)
    assert m['overshoot'] == pytest.approx((1 + extremum) * abs(math.cos(extremum)), rel=1e-6)
    assert m['settle_s'] is None


def test_a_run_that_never_crosses_or_settles_says_so():
    t = np.linspace(0.0, 1.0, 11)
    m = transient_metrics(t, np.ones(11), None)
    assert m == {'enter_3sigma_s': None, 'zero_crossing_s': None, 'overshoot': 0.0, 'settle_s': None}


def test_the_noise_floor_is_what_zero_mean_noise_gives_the_mean_error_reading():
    rng = np.random.default_rng(0)
    runs, steps, sigma = 100, 4000, 0.3
    errors = rng.normal(0.0, sigma, (runs, steps))
    reading = np.abs(errors.mean(axis=0)).mean()   # SimulationResult.mean_error's formula
    assert reading == pytest.approx(float(noise_floor(sigma, runs)), rel=0.03)
    assert float(noise_floor(1.0, 100)) == pytest.approx(0.0798, abs=1e-4)


def test_every_figure_the_report_shows_is_committed_within_the_budget():
    from snn_tools.experiments.tables import FIGURE_BUDGET_BYTES
    report = (RESULTS / 'REPORT.md').read_text()
    links = re.findall(r'!\[[^\]]*\]\(([^)]+)\)', report)
    assert links, 'REPORT.md shows no figure'
    for link in links:
        assert link.startswith('figures/'), link
        assert (RESULTS / link).is_file(), f'{link} is linked by REPORT.md but missing'
    total = sum(path.stat().st_size for path in (RESULTS / 'figures').glob('*.png'))
    assert total <= FIGURE_BUDGET_BYTES
