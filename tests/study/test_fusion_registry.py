"""One list of late-fusion methods (`fusion.boxes.FUSION_METHODS`) and one normalisation of their names
(`fusion.boxes.method_name`): a method registered there is accepted by every command and config
section that takes one, and `study/` spells no list of method names of its own (issue 47 item 4)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pytest

from fusion.boxes import FUSION_METHODS, HYDRAFUSION_PARAMS, method_label, method_labels, method_name
from sim.errors import UserError

ROOT = Path(__file__).resolve().parents[2]


def keep_all(boxes_list, scores_list, labels_list, weights=None, **_params):
    """A method that fuses nothing: every source's boxes, highest score first."""
    boxes = np.concatenate([np.asarray(b, float).reshape(-1, 4) for b in boxes_list])
    scores = np.concatenate([np.asarray(s, float) for s in scores_list])
    labels = np.concatenate([np.asarray(v) for v in labels_list])
    order = np.argsort(-scores, kind="stable")
    return boxes[order], scores[order], labels[order]


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(FUSION_METHODS._entries, "keep_all", keep_all)
    monkeypatch.setitem(HYDRAFUSION_PARAMS, "keep_all", {})
    return "keep-all"


def test_names_and_labels_are_one_normalisation():
    assert method_labels() == [n.replace("_", "-") for n in FUSION_METHODS.names()] == ["nms", "soft-nms", "wbf"]
    for name in FUSION_METHODS.names():
        assert method_name(name) == method_name(method_label(name)) == name
    with pytest.raises(ValueError, match=r"unknown fusion method 'softnms' \(choose from: nms, soft-nms, wbf\)"):
        method_name("softnms")


def test_a_method_registered_in_fusion_boxes_is_taken_everywhere(registered):
    from fusion.late import Detections, fuse
    from sensors.rig import load_profile, make_calibration, profile_names
    from study.cli import fusion_arg
    from study.engine.scoring import fusion_method
    from study.pipeline.config import _fusion

    assert registered in method_labels() and fusion_arg(registered) == registered
    assert fusion_method(registered) == "keep_all" and fusion_method("keep_all") == "keep_all"
    _fusion("evaluate.fusion", registered, "validation")  # the study config's three sections take it
    with pytest.raises(UserError, match="keep-all"):
        _fusion("crossover.fusion", "bogus")
    with pytest.raises(argparse.ArgumentTypeError, match="keep-all"):
        fusion_arg("bogus")
    with pytest.raises(UserError, match="keep-all"):
        fusion_method("bogus")
    # and the one fusion path runs it: two camera-frame branches, nothing suppressed
    calib = make_calibration(load_profile(profile_names()[0]))
    a = Detections(np.array([[10.0, 10, 50, 50]]), np.array([0.9]), np.array([1]))
    b = Detections(np.array([[12.0, 11, 51, 49]]), np.array([0.8]), np.array([1]))
    out = fuse({"a": a, "b": b}, {"a": "camera_right", "b": "camera_right"}, calib, method="keep_all")
    assert np.allclose(out.scores, [0.9, 0.8]) and np.allclose(out.boxes, [[10, 10, 50, 50], [12, 11, 51, 49]])
    assert len(fuse({"a": a, "b": b}, {"a": "camera_right", "b": "camera_right"}, calib, method="nms").scores) == 1


def test_study_spells_no_list_of_fusion_methods_of_its_own():
    """Every list of method names in study/ comes from the registry: a literal such as
    ("nms", "soft-nms", "wbf") or a `.replace("-", "_")` on a method name would be a second one."""
    pattern = re.compile(r"""["'](nms|soft[-_]nms|wbf)["']\s*[,:]\s*["'](nms|soft[-_]nms|wbf)["']""")
    hits = []
    for path in sorted((ROOT / "study").rglob("*.py")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line) or ("fusion" in line and '.replace("-", "_")' in line):
                hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not hits, "\n".join(hits)


def test_no_module_imports_another_modules_private_name():
    """Issue 47 item 4: what one module uses of another is public (`from x import _y` and `x._y` are not)."""
    import ast

    ours = ("study", "fusion", "sensors", "sim")
    hits = []
    for path in sorted(p for d in ours for p in (ROOT / d).rglob("*.py")):
        tree = ast.parse(path.read_text())
        modules = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names
                   if a.name.split(".")[0] in ours}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in ours:
                hits += [f"{path.relative_to(ROOT)}:{node.lineno}: from {node.module} import {a.name}"
                         for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                base = ast.unparse(node.value)
                if base in modules:
                    hits.append(f"{path.relative_to(ROOT)}:{node.lineno}: {base}.{node.attr}")
    assert not hits, "\n".join(hits)
