"""Gates written outside hydrabench, as a user writes them (docs/nuscenes.md, "Score your own gate"):
plain callables that read a `study.experiments.gate_protocol.GateFrame` and import nothing from hydrabench.
tests/study/test_gate_protocol.py loads them with `hydrabench score --gate
tests.study.data.example_gates:NAME`."""

import math

FOG_VISIBILITY_M = 1000.0
"""Below this visibility (a forward-scatter sensor's reading) the gate trusts the radar alone."""


def by_visibility(frame):
    """A branch set from a measured quantity: the radar alone in fog, every branch otherwise."""
    if frame.weather["visibility_m"] < FOG_VISIBILITY_M and "radar" in frame.branches:
        return ["radar"]
    return list(frame.branches)


class MostConfident:
    """A score per branch: the summed confidence of the branch's detections on the frame (higher =
    better). Keeps state, as a temporal gate would: the frames it has seen, in order."""

    def __init__(self):
        self.seen = []

    def __call__(self, frame):
        self.seen.append(frame.index)
        return {b: float(d.scores.sum()) for b, d in frame.detections.items()}


SEEN = []
"""What `recorder` was given: one GateFrame per call."""


def recorder(frame):
    """Keeps every frame it is given and fuses every branch."""
    SEEN.append(frame)
    return tuple(frame.branches)


# ----- gates that break the protocol: each must be refused with one line naming it and the frame


def unknown_branch(frame):
    return ["sonar"]


def empty_set(frame):
    return []


def nan_score(frame):
    return {b: (math.nan if i == 0 else 1.0) for i, b in enumerate(frame.branches)}


def missing_score(frame):
    return {frame.branches[0]: 1.0}


def wrong_type(frame):
    return frame.branches[0]  # a name, not a list of names


def none_returned(frame):
    return None


def twice(frame):
    return [frame.branches[0], frame.branches[0]]


def raises(frame):
    raise RuntimeError("the rain sensor is offline")


NOT_A_GATE = 42


class NeedsArguments:
    def __init__(self, threshold):
        self.threshold = threshold

    def __call__(self, frame):
        return list(frame.branches)
