"""fusion.crossover: the crossing of a synthetic curve with a known crossing, on linear and log axes,
censoring, and the conservative first resolved step."""

import math

import numpy as np
import pytest

from fusion.crossover import crossing_of, crossover, order_steps


def test_crossing_is_interpolated_where_the_line_meets_zero():
    x = np.arange(1.0, 11.0)
    assert crossing_of(x, 0.05 - 0.01 * x) == (pytest.approx(5.0), "crossed")
    assert crossing_of(x, 0.05 - 0.011 * x)[0] == pytest.approx(0.05 / 0.011)
    assert crossing_of(x, np.full(10, 0.01)) == (pytest.approx(float("nan"), nan_ok=True), "none")
    assert crossing_of(x, -0.01 - 0.0 * x) == (1.0, "at_mildest")
    # the first crossing counts, a later return above 0 does not undo it
    assert crossing_of([1, 2, 3, 4], [0.1, -0.1, 0.2, -0.2]) == (pytest.approx(1.5), "crossed")


def test_log_axis_for_fog_visibility():
    """Visibility falls as fog thickens: ordered mild to strong it decreases; d = 0.02 ln(v / 120)
    is 0 at 120 m, which lies between the steps 150 and 75 m: the log-axis interpolation finds it
    exactly, a linear one would not."""
    vis = np.array([800.0, 400.0, 150.0, 75.0, 40.0])
    assert list(order_steps([75.0, 800.0, 40.0, 400.0, 150.0], "lower")) == [1, 3, 4, 0, 2]
    d = 0.02 * np.log(vis / 120.0)
    v, kind = crossing_of(vis, d, scale="log")
    assert kind == "crossed" and v == pytest.approx(120.0)
    assert crossing_of(vis, d, scale="linear")[0] != pytest.approx(120.0, rel=1e-3)


def test_crossover_of_noisy_draws_covers_the_known_crossing():
    rng = np.random.default_rng(0)
    x = np.arange(1.0, 11.0)
    true = 0.05 - 0.01 * x
    draws = true + rng.normal(0, 0.004, size=(2000, 10))
    c = crossover(x, true, draws)
    assert c.crossing == pytest.approx(5.0) and c.crossing_kind == "crossed"
    lo, hi = c.crossing_interval
    assert lo < 5.0 < hi and hi - lo < 2.0
    # conservative: the first step whose interval is below 0 lies past the crossing (d = -0.01 at 6
    # is 2.5 sd below 0)
    assert c.first_resolved_below == 6.0
    assert c.censored == {"at_or_before_mildest": 0.0, "beyond_strongest": 0.0}
    assert c.as_dict()["crossing"] == pytest.approx(5.0)


def test_crossover_that_never_happens_is_open_and_says_so():
    rng = np.random.default_rng(1)
    x = np.array([0.5, 2.5, 5.0, 10.0, 25.0])
    flat = np.full(5, 0.03)
    c = crossover(x, flat, flat + rng.normal(0, 0.01, (500, 5)), scale="log")
    assert c.crossing_kind == "none" and math.isnan(c.crossing) and c.first_resolved_below is None
    assert c.crossing_interval == (None, None) and c.censored["beyond_strongest"] > 0.9


def test_crossover_refuses_unordered_steps_and_bad_shapes():
    with pytest.raises(ValueError, match="monotone"):
        crossover([1, 3, 2], [0, 0, 0], np.zeros((3, 3)))
    with pytest.raises(ValueError):
        crossover([1, 2, 3], [0, 0], np.zeros((3, 3)))
    with pytest.raises(ValueError):
        order_steps([1, 2], "worse")
