"""The one rounding rule of stored results and the one way tables print numbers (`study.numbers`)."""

import math

import numpy as np

from study.engine.gate_tables import selection_rates
from study.numbers import interval_text, number_text, rounded, rounded_interval, significant


def test_rounded_keeps_four_decimals_and_maps_what_json_cannot_hold_to_none():
    assert rounded(0.123456) == 0.1235 and rounded(np.float32(0.5)) == 0.5 and rounded(3) == 3.0
    assert rounded(2.0 / 3.0, 1) == 0.7 and isinstance(rounded(np.float64(1.0)), float)
    assert rounded(None) is None and rounded(math.nan) is None and rounded(-math.inf) is None
    assert rounded_interval((0.123456, np.float64(0.98765))) == [0.1235, 0.9877]
    assert rounded_interval(None) is None and rounded_interval((math.nan, 1.0)) == [None, 1.0]


def test_number_text_and_interval_text():
    assert [number_text(v) for v in (None, 0.5, 0.0, 12.34567, 1234.6, 0.00123, 7, "radar")] == \
        ["-", "0.500", "0.000", "12.346", "1235", "1.2e-03", "7", "radar"]
    assert number_text(np.float32(0.25)) == "0.250" and number_text(np.int64(3)) == "3"
    assert interval_text((0.1, 0.25)) == "[0.100, 0.250]" and interval_text(None) == "-"
    assert interval_text((-0.0, -0.0123), signed=True) == "[+0.000, -0.012]"


def test_selection_rates_are_percent_of_frames_to_a_tenth():
    frames = [("radar",), ("radar", "lidar"), ("lidar",)]
    assert selection_rates(frames, ["radar", "lidar", "camera_right"]) == {"radar": 66.7, "lidar": 66.7,
                                                                           "camera_right": 0.0}
    assert selection_rates([], ["radar"]) == {"radar": 0.0}


def test_significant_keeps_figures_not_decimals():
    # a ratio far below 1 keeps its three figures: two fixed decimals would move 0.0641 to 0.06 (6 %)
    assert significant(0.064149) == 0.0641 and significant(1.9349) == 1.93 and significant(123.456, 4) == 123.5
    assert significant(None) is None and significant(float("nan")) is None and significant(float("inf")) is None
