"""Gates from outside: the protocol a gate written anywhere follows to be scored by `hydrabench score`
(docs/nuscenes.md, "Score your own gate").

A gate is a callable, called once per scored frame, in dataset order (sequence by sequence, in time
order within one), with one `GateFrame`:

    choice = gate(frame)

and returns either

- a branch set: a list, tuple or set of branch names (at least one; each branch once), fused on that
  frame as given; or
- a score per branch: a dict branch name -> finite number, higher = better, one for every branch;
  the k highest are fused (`--k`, default `DEFAULT_K` as `hydrabench compare` gives its built-in
  gates; ties keep the branch order, as `fusion.nets.branch_gates.top_k` ranks predicted losses).

A class is instantiated once, without arguments, before the first frame, so a gate can keep state
(a temporal gate) in `self`. Each frame's choice becomes one entry of a per-frame selection, scored
exactly as a selection file is (`study.experiments.external.score_external`): one path, the same intervals.

What a gate reads (`GateFrame`) is what a car could have when it chooses: the road type its map
gives, the readings of its weather and light sensors, its clock, its calibration, and every branch's
detections on the frame. Never the labels, the context label, the condition's severity level or the
lens coverage: those are the simulator's (see `GateFrame` for why each field is in or out).

Loading (`load_gate`): `[NAME=]package.module:attr` (attr may be dotted: `module:Class.method`),
importable from sys.path or the current directory; or `[NAME=]ENTRY`, the entry point ENTRY of the
group `hydrabench.gates` (a package declares `[project.entry-points."hydrabench.gates"]
mygate = "mypkg.gates:MyGate"`). Every failure is one line naming the gate (and the frame).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import math
import numbers
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from sim.errors import UserError

ENTRY_POINT_GROUP = "hydrabench.gates"
DEFAULT_K = 2
"""Branches a score-returning gate keeps per frame when `--k` is not given: `hydrabench compare`'s
default for its built-in gates (capped at the number of branches)."""

WEATHER_READINGS = ("visibility_m", "rain_mm_h", "snow_mm_h", "illuminance_lux")
"""The weather record's quantities a car measures (`fusion.physical_gate.CAR_QUANTITY`): a
forward-scatter visibility sensor, a rain sensor or disdrometer (rain, and snow as water
equivalent), an ambient light sensor."""
LIGHT_READINGS = ("sun_elevation_deg", "headlights_on", "street_lamps_on")
"""The light record: the sun's elevation (from the clock and the position), whether the car's own
headlights are on, whether the street lamps are lit (as the camera sees them)."""

_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+-]*$")


@dataclass(frozen=True)
class GateFrame:
    """What a gate from outside reads for one frame.

    Fields:
        index: the frame's index in the dataset (the selection file's key).
        sample_token: its nuScenes sample token when `--export` is given, else None: the key to the
            sensor files of the export (images, lidar, radar points) a gate may read. The export's
            annotations are labels: a gate that reads them is not a gate.
        sequence: the id of the drive the frame belongs to; a new id starts a new drive.
        time_s: [s] the frame's time since the drive started.
        road: the road type of the map: "city", "junction", "motorway" or "rural".
        weather: `WEATHER_READINGS` -> reading: visibility [m] (meteorological optical range, every
            extinction together), rain and snow rates [mm/h, water equivalent], illuminance [lx].
        light: `LIGHT_READINGS` -> sun elevation [deg], headlights on, street lamps on.
        calibration: the rig's calibration (`sensors.rig.Calibration`): extrinsics, intrinsics.
        detections: branch name -> its detections in the right camera (`fusion.late.Detections`:
            boxes (N, 4) [x1, y1, x2, y2] px, scores (N,), labels (N,) RADIATE class ids 1..8,
            merged as the scored classes are when nuScenes files are read), read-only.
        branch_sensors: branch name -> the sensors it used ("camera_right", "lidar", "radar"), in
            the order the branches were given.

    Left out, on purpose: the labels and anything drawn from them; the context label (it names the
    conditions the simulator was asked for: a car reads the quantities above, which fall in the
    severity table's ranges, not a word); the severity level (the benchmark's dial, an index into
    that table; a gate told it is `knowledge_informed`, an oracle); each lens's coverage by drops
    or snow (the simulator's state: a car would have to infer it from the images, which a gate
    may read through `sample_token`); the frame's counterfactual twin.
    """

    index: int
    sample_token: str | None
    sequence: str
    time_s: float
    road: str
    weather: Mapping[str, float]
    light: Mapping[str, Any]
    calibration: Any
    detections: Mapping[str, Any]
    branch_sensors: Mapping[str, tuple[str, ...]]

    @property
    def branches(self) -> tuple[str, ...]:
        return tuple(self.branch_sensors)


def _read_only(d):
    from fusion.late import Detections

    arrays = [np.array(a) for a in (d.boxes, d.scores, d.labels)]
    for a in arrays:
        a.setflags(write=False)
    return Detections(*arrays)


def gate_frame(meta: dict, per: dict, branch_sensors: dict, sample_token: str | None = None) -> GateFrame:
    """The `GateFrame` of one frame: `meta` (the dataset's per-frame meta with "dataset_index") and
    `per` (branch -> Detections in the right camera)."""
    from sensors.rig import Calibration

    frame = int(meta["dataset_index"])
    try:
        weather = {q: float(meta["weather"][q]) for q in WEATHER_READINGS}
        light = {q: meta["light"][q] for q in LIGHT_READINGS}
        road, sequence, time_s = str(meta["layout"]), str(meta["sequence_id"]), float(meta["timestamp_s"])
    except (KeyError, TypeError) as exc:
        raise UserError(f"frame {frame}: its meta has no {exc} (a gate reads the road, weather and light "
                        "records of a generated dataset)") from None
    return GateFrame(index=frame, sample_token=sample_token, sequence=sequence, time_s=time_s, road=road,
                     weather=MappingProxyType(weather), light=MappingProxyType(light),
                     calibration=Calibration.from_dict(meta["calibration"]),
                     detections=MappingProxyType({b: _read_only(d) for b, d in per.items()}),
                     branch_sensors=MappingProxyType({b: tuple(s) for b, s in branch_sensors.items()}))


# ----- loading ------------------------------------------------------------------------------------


def split_spec(spec: str) -> tuple[str, str]:
    """`[NAME=]TARGET` -> (NAME, TARGET); NAME defaults to the entry point's name or the attribute's
    last part. UserError for an empty or malformed spec."""
    text = str(spec).strip()
    name, sep, target = text.partition("=")
    if not sep:
        name, target = "", text
    target = target.strip()
    if not target:
        raise UserError(f"--gate {spec!r}: expected [NAME=]package.module:attr or [NAME=]ENTRY (an entry point of "
                        f"the group {ENTRY_POINT_GROUP})")
    if ":" in target:
        module, _, attr = target.partition(":")
        parts = attr.split(".")
        if not module or not all(p.isidentifier() for p in parts) or not all(
                p.isidentifier() for p in module.split(".")):
            raise UserError(f"--gate {spec}: expected package.module:attr (identifiers, attr may be dotted), got "
                            f"{target!r}")
        default = parts[-1]
    else:
        default = target
    name = name.strip() or default
    if not _NAME.match(name):
        raise UserError(f"--gate {spec}: the gate's name {name!r} must be letters, digits, _ . + - (NAME=...)")
    return name, target


def _import_attr(spec: str, target: str):
    module, _, attr = target.partition(":")
    cwd = str(Path.cwd())
    added = cwd not in sys.path
    if added:
        sys.path.append(cwd)  # a gate module beside the user's files, as `python -m` would find it
    try:
        obj = importlib.import_module(module)
    except Exception as exc:  # the user's module: any error while importing it is theirs
        raise UserError(f"--gate {spec}: cannot import {module} ({type(exc).__name__}: {_one_line(exc)})") from None
    finally:
        if added and cwd in sys.path:
            sys.path.remove(cwd)
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise UserError(f"--gate {spec}: {module} has no attribute {attr!r}")
        obj = getattr(obj, part)
    return obj


def _entry_point(spec: str, target: str):
    try:
        eps = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
    except Exception as exc:
        raise UserError(f"--gate {spec}: cannot list the entry points of {ENTRY_POINT_GROUP} "
                        f"({type(exc).__name__}: {_one_line(exc)})") from None
    found = [ep for ep in eps if ep.name == target]
    if not found:
        names = sorted({ep.name for ep in eps})
        have = f"installed: {', '.join(names)}" if names else "none is installed"
        raise UserError(f"--gate {spec}: no entry point {target!r} in the group {ENTRY_POINT_GROUP} ({have}); "
                        "or give package.module:attr")
    try:
        return found[0].load()
    except Exception as exc:
        raise UserError(f"--gate {spec}: entry point {target!r} ({found[0].value}) does not load "
                        f"({type(exc).__name__}: {_one_line(exc)})") from None


def load_gate(spec: str) -> tuple[str, Any]:
    """(name, gate callable) of `[NAME=]package.module:attr` or `[NAME=]ENTRY` (module docstring). A
    class is instantiated once without arguments. UserError, one line, for anything that fails."""
    name, target = split_spec(spec)
    obj = _import_attr(spec, target) if ":" in target else _entry_point(spec, target)
    if isinstance(obj, type):
        try:
            obj = obj()
        except Exception as exc:
            raise UserError(f"--gate {spec}: {obj.__name__}() failed ({type(exc).__name__}: {_one_line(exc)}); a "
                            "gate class is built without arguments") from None
    if not callable(obj):
        raise UserError(f"--gate {spec}: {target} is a {type(obj).__name__}, not a callable gate (gate(frame) -> "
                        "branch names or a score per branch)")
    return name, obj


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 300 else text[:297] + "..."


# ----- the choice -------------------------------------------------------------------------------


def branch_set(names, branches, where: str, allow_empty: bool = False) -> tuple[str, ...]:
    """`names` (a list, tuple or set of branch names) as a tuple in `branches` order. UserError
    starting with `where` for an unknown branch, a branch twice, or (unless `allow_empty`) none."""
    if not isinstance(names, list | tuple | set | frozenset) or not all(isinstance(b, str) for b in names):
        raise UserError(f"{where}: not a list of branch names (got {_describe(names)})")
    names = list(names)
    bad = [b for b in names if b not in branches]
    if bad:
        raise UserError(f"{where}: unknown branch {bad[0]!r} (branches: {', '.join(branches)})")
    twice = sorted({b for b in names if names.count(b) > 1})
    if twice:
        raise UserError(f"{where}: branch {twice[0]!r} named twice")
    if not names and not allow_empty:
        raise UserError(f"{where}: an empty branch set (a gate keeps at least one branch)")
    return tuple(b for b in branches if b in names)


def top_scored(scores: Mapping, branches, k: int, where: str) -> tuple[str, ...]:
    """The `k` branches with the highest score (ties in `branches` order), in branch order. UserError
    starting with `where` for an unknown branch, a missing one, or a score that is not a finite number."""
    bad = [b for b in scores if b not in branches]
    if bad:
        raise UserError(f"{where}: unknown branch {bad[0]!r} (branches: {', '.join(branches)})")
    missing = [b for b in branches if b not in scores]
    if missing:
        raise UserError(f"{where}: no score for branch {missing[0]!r} (a score per branch: one for each of "
                        f"{', '.join(branches)})")
    values = []
    for b in branches:
        v = scores[b]
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
            raise UserError(f"{where}: the score of branch {b!r} is {v!r}, not a finite number")
        values.append(float(v))
    order = np.argsort(-np.asarray(values), kind="stable")[:k]  # highest first; ties keep branch order
    return tuple(branches[j] for j in sorted(order))


def _describe(value) -> str:
    text = repr(value)
    return f"a {type(value).__name__}: {text if len(text) <= 60 else text[:57] + '...'}"


def choice_of(result, branches, k: int, where: str) -> tuple[str, ...]:
    """A gate's return value as the branch tuple fused on the frame (module docstring)."""
    if isinstance(result, Mapping):
        if not all(isinstance(b, str) for b in result):
            raise UserError(f"{where}: a score dict's keys must be branch names (got {_describe(result)})")
        return top_scored(result, list(branches), k, where)
    if isinstance(result, list | tuple | set | frozenset):
        return branch_set(result, list(branches), where)
    raise UserError(f"{where}: returned {_describe(result)}; expected a list of branch names or a dict branch -> "
                    "score")


def gate_k(k, n_branches: int, given: bool) -> int:
    """The k of score-returning gates: `k` (an int or "all", already parsed) or, not given, DEFAULT_K
    capped at the number of branches."""
    if not given:
        return min(DEFAULT_K, n_branches)
    return n_branches if k == "all" else int(k)


def gate_selection(name: str, gate, ext, index=None, k: int = DEFAULT_K) -> list[tuple[str, ...]]:
    """Per scored frame of `ext` (`study.experiments.external.ExternalSet`), the branches `gate` chooses: the
    per-frame selection a selection file would give. `index`: the export's (for sample tokens)."""
    out = []
    for meta, per in ext.per_frame:
        frame = int(meta["dataset_index"])
        token = index.token_of.get(frame) if index is not None else None
        view = gate_frame(meta, per, ext.branch_sensors, token)
        where = f"gate {name}: frame {frame}"
        try:
            result = gate(view)
        except Exception as exc:  # the user's gate: any error in it is reported as theirs, on one line
            raise UserError(f"{where}: raised {type(exc).__name__}: {_one_line(exc)}") from None
        out.append(choice_of(result, ext.branches, k, where))
    return out
