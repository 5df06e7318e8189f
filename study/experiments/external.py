"""Detections and gates made outside hydrabench, scored by the one path (`hydrabench score`).

Inputs, one file per branch (a sensor configuration of the user's detector):

- nuScenes detection-results JSON (`{"meta": {...}, "results": {sample_token: [box, ...]}}`) on a
  nuScenes export of the dataset (`hydrabench export nuscenes`): 3D boxes in the log's global frame.
  The `meta` block's use_camera / use_lidar / use_radar name the sensors the file used; the branch is
  named by the user (NAME=FILE) or by those sensors ("camera+lidar"). Each box is brought into the
  frame's ego frame by the frame's stored ego pose (and the export's map offset), its 8 corners
  projected into the right camera by the frame's stored calibration (`sensors.rig.project_box3d`,
  the projection the own BEV branches' Appendix A mapping ends with and the `reference` protocol's
  ground truth is made with). A box counts in the camera as an object does there: its centre in
  front of the camera and its projection meeting the image.
- COCO results JSON (`[{image_id, category_id, bbox [x, y, w, h], score}]`) of a camera-only 2D
  detector on the right camera, with `hydrabench export coco`'s numbering: image_id = frame index + 1,
  category_id = RADIATE class id (1..8).

Classes: nuScenes detection names do not tell a van from a car, nor a group of pedestrians from one
(`sensors.export.nuscenes.CLASS_TABLE`), so when any nuScenes file is scored the ground truth and
every detection are scored in the merged classes (van -> car, group_of_pedestrians -> pedestrian:
`MERGED`). COCO-only sets keep the eight classes.

Frames a file leaves out: a nuScenes file must list every scored frame's sample token (an empty
list for a frame without detections), as the nuScenes devkit asks; one that leaves frames out is
refused, or with `missing="empty"` those frames are scored as frames without detections and counted
in the result (`left_out`). A COCO results file lists detections only, so a frame with no record is
a frame without detections (the format cannot say more).

A selection file (JSON: frame index or sample token -> list of branch names) is the simplest gate
from outside: per frame, the branches to fuse. A gate in code (`study.experiments.gate_protocol`: a callable
that reads what a car measures and the detections, and returns a branch set or a score per branch)
is turned into the same per-frame selection and scored by the same path. Learned gates read the own
networks' stem features and the optimal gate the own branches' Faster R-CNN losses: neither exists
for external detections, so they are not scored here. The nuScenes devkit's own metrics of the
nuScenes files: `study.experiments.nuscenes_metrics`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import UserError

# nuScenes detection name -> RADIATE class (the inverse of CLASS_TABLE, on its merged classes)
NAME_TO_CLASS = {"car": "car", "truck": "truck", "bus": "bus", "motorcycle": "motorbike", "bicycle": "bicycle",
                 "pedestrian": "pedestrian"}
MERGED = {"van": "car", "group_of_pedestrians": "pedestrian"}
SENSOR_FLAGS = (("use_camera", "camera_right"), ("use_lidar", "lidar"), ("use_radar", "radar"))
MISSING = ("refuse", "empty")


@dataclass
class ExternalSet:
    """Detections from outside, all in the right camera: `per_frame` [(meta, {branch: Detections})],
    the branches' sensors and source files, whether classes are merged, frames each file left out,
    and the branches read from nuScenes results (`nuscenes_files`: branch -> file)."""

    per_frame: list
    branch_sensors: dict
    sources: dict
    merged: bool
    left_out: dict = field(default_factory=dict)
    nuscenes_files: dict = field(default_factory=dict)

    @property
    def branches(self) -> list[str]:
        return list(self.branch_sensors)


def load_json(path: Path, what: str):
    """JSON of `path`; a key twice in one object is refused (json.loads would keep the last)."""
    def pairs(items):
        seen = {}
        for k, v in items:
            if k in seen:
                raise UserError(f"{path}: {what}: key {k!r} appears twice in one object")
            seen[k] = v
        return seen

    try:
        return json.loads(Path(path).read_text(), object_pairs_hook=pairs)
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    except ValueError as exc:
        raise UserError(f"{path}: not JSON ({exc})") from None


def _quaternion_matrix(q) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def box_corners_ego(translation, size, rotation, ego_from_global: np.ndarray) -> np.ndarray:
    """(8, 3) corners in the ego frame of a nuScenes box (global centre, size (w, l, h), rotation
    (w, x, y, z)); the box's x axis runs along its length."""
    width, length, height = (float(v) for v in size)
    local = np.array([[sx * length / 2, sy * width / 2, sz * height / 2] for sz in (-1, 1) for sx, sy in
                      ((1, 1), (1, -1), (-1, -1), (-1, 1))])
    g = local @ _quaternion_matrix(rotation).T + np.asarray(translation, float)
    return g @ ego_from_global[:3, :3].T + ego_from_global[:3, 3]


def to_camera(corners_ego: np.ndarray, calib, camera: str = "camera_right"):
    """The image box of a 3D box in `camera` (None when it does not count there: centre not in front
    of the camera, or its projection misses the image), as `sensors.labels.reference_labels` draws
    the ground truth."""
    from sensors.rig import project_box3d

    cam = calib.camera(camera)
    _, depth = cam.project(corners_ego.mean(axis=0)[None])
    if not depth[0] > 0:
        return None
    return project_box3d(corners_ego, cam)


class ExportIndex:
    """What a nuScenes export says about the frames: sample token -> frame index, and per frame the
    global-from-world offset of its log (`hydrabench export nuscenes`)."""

    def __init__(self, root, reader):
        from sensors.export.nuscenes import VERSION, dataset_salt

        root = Path(root)
        info_path = root / "hydrabench_export.json"
        info = load_json(info_path, "export summary") if info_path.is_file() else None
        if not isinstance(info, dict) or "dataset_salt" not in info:
            raise UserError(f"--export {root}: not a hydrabench nuScenes export (no hydrabench_export.json; see "
                            "hydrabench export nuscenes)")
        if info["dataset_salt"] != dataset_salt(reader.manifest, False):
            raise UserError(f"--export {root}: an export of another dataset than {reader.root} (or of its clear "
                            "twins): export this one with hydrabench export nuscenes")
        tables = {n: load_json(root / VERSION / f"{n}.json", n) for n in ("sample", "scene", "log", "map")}
        offset_of_log = {}
        for m in tables["map"]:
            for log in m["log_tokens"]:
                offset_of_log[log] = np.asarray(m["hydrabench"]["global_from_world_offset_m"], float)
        log_of_scene = {s["token"]: s["log_token"] for s in tables["scene"]}
        self.frame_of = {s["token"]: int(s["hydrabench"]["frame"]) for s in tables["sample"]}
        name_of_scene = {s["token"]: s["name"] for s in tables["scene"]}
        self.scene_of = {int(s["hydrabench"]["frame"]): name_of_scene[s["scene_token"]] for s in tables["sample"]}
        self.splits = load_json(root / VERSION / "splits.json", "splits")
        self.token_of = {f: t for t, f in self.frame_of.items()}
        self.offset = {int(s["hydrabench"]["frame"]): offset_of_log[log_of_scene[s["scene_token"]]]
                       for s in tables["sample"]}


def split_frames(index: ExportIndex | None, reader, split: str) -> list[int]:
    """The frames of `split`: "all", or a split of the export's splits.json (its scenes' frames)."""
    if split == "all":
        return list(range(len(reader)))
    if index is None:
        raise UserError(f"--split {split}: splits are the export's (splits.json): give --export DIR")
    if split not in index.splits:
        raise UserError(f"--split {split}: not a split of the export (it has: {', '.join(sorted(index.splits))}, all)")
    scenes = set(index.splits[split])
    return sorted(f for f, s in index.scene_of.items() if s in scenes)


def _finite(values, n: int) -> bool:
    try:
        return len(values) == n and all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)
    except TypeError:
        return False


def read_nuscenes(path, index: ExportIndex, metas: dict, missing: str = "refuse") -> tuple[dict, tuple, list]:
    """{frame: Detections in the right camera} of one results file on the frames `metas` ({frame:
    meta}), its sensors (from `meta`) and the frames it left out. UserError naming the file and the
    record for anything damaged."""
    from fusion.late import Detections
    from sensors.rig import Calibration
    from sim.actors import CLASSES

    path = Path(path)
    doc = load_json(path, "results")
    if not isinstance(doc, dict) or not isinstance(doc.get("meta"), dict):
        raise UserError(f"{path}: no 'meta' block (nuScenes results name the sensors they used there)")
    flags = [k for k, _ in SENSOR_FLAGS if k not in doc["meta"]]
    if flags:
        raise UserError(f"{path}: meta has no {flags[0]!r} (use_camera, use_lidar, use_radar name the sensors)")
    sensors = tuple(s for k, s in SENSOR_FLAGS if doc["meta"][k])
    if not sensors:
        raise UserError(f"{path}: meta says no camera, lidar or radar was used")
    results = doc.get("results")
    if not isinstance(results, dict):
        raise UserError(f"{path}: no 'results' object (sample token -> list of boxes)")
    unknown = [t for t in results if t not in index.frame_of]
    if unknown and len(unknown) == len(results):
        raise UserError(f"{path}: a file for another dataset: none of its {len(results)} sample tokens is in the "
                        f"export (first: {unknown[0]!r})")
    if unknown:
        raise UserError(f"{path}: results[{unknown[0]!r}]: unknown sample token (not in the export)")
    given = {index.frame_of[t] for t in results}
    left = sorted(f for f in metas if f not in given)
    if left and missing == "refuse":
        raise UserError(f"{path}: leaves out {len(left)} of the {len(metas)} scored frames (first: frame {left[0]}, "
                        f"sample {index.token_of.get(left[0])!r}); list them with [] or give --missing empty")
    out = {}
    for token, boxes in results.items():
        frame = index.frame_of[token]
        if frame not in metas:
            continue  # a frame outside the scored split
        if not isinstance(boxes, list):
            raise UserError(f"{path}: results[{token!r}]: not a list of boxes")
        meta = metas[frame]
        calib = Calibration.from_dict(meta["calibration"])
        world_from_ego = np.asarray(meta["ego_pose"], float)
        global_from_ego = world_from_ego.copy()
        global_from_ego[:3, 3] += index.offset[frame]
        ego_from_global = np.linalg.inv(global_from_ego)
        bx, sc, lb = [], [], []
        for j, b in enumerate(boxes):
            where = f"{path}: results[{token!r}][{j}]"
            if not isinstance(b, dict):
                raise UserError(f"{where}: not a box object")
            if b.get("sample_token") != token:
                raise UserError(f"{where}: sample_token {b.get('sample_token')!r} is not the key it is listed under")
            if not _finite(b.get("translation"), 3):
                raise UserError(f"{where}: translation must be 3 finite numbers")
            if not _finite(b.get("size"), 3) or min(b["size"]) <= 0:
                raise UserError(f"{where}: size must be 3 finite numbers > 0, got {b.get('size')!r}")
            if not _finite(b.get("rotation"), 4) or not any(b["rotation"]):
                raise UserError(f"{where}: rotation must be a quaternion (w, x, y, z) of 4 finite numbers, not 0")
            name = b.get("detection_name")
            if name not in NAME_TO_CLASS:
                raise UserError(f"{where}: detection_name {name!r} is not in the class table "
                                f"({', '.join(NAME_TO_CLASS)}; docs/nuscenes.md)")
            score = b.get("detection_score")
            if not _finite([score], 1) or score < 0:
                raise UserError(f"{where}: detection_score must be a finite number >= 0, got {score!r}")
            box = to_camera(box_corners_ego(b["translation"], b["size"], b["rotation"], ego_from_global), calib)
            if box is not None:
                bx.append(box)
                sc.append(float(score))
                lb.append(CLASSES.index(NAME_TO_CLASS[name]) + 1)
        out[frame] = Detections(np.array(bx, float).reshape(-1, 4), np.array(sc, float), np.array(lb, np.int64))
    for f in left:
        out[f] = Detections.empty()
    return out, sensors, left


def read_coco(path, metas: dict, frames_in_data: int) -> dict:
    """{frame: Detections in the right camera} of a COCO results file (image_id = frame + 1,
    category_id = RADIATE class id). UserError naming the file and the record when damaged."""
    from fusion.late import Detections
    from sim.actors import CLASSES

    path = Path(path)
    doc = load_json(path, "COCO results")
    if not isinstance(doc, list):
        raise UserError(f"{path}: COCO results are a list of detections, got a {type(doc).__name__}")
    rows: dict = {f: ([], [], []) for f in metas}
    for j, r in enumerate(doc):
        where = f"{path}: record {j}"
        if not isinstance(r, dict):
            raise UserError(f"{where}: not a detection object")
        img = r.get("image_id")
        if not isinstance(img, int) or not 1 <= img <= frames_in_data:
            raise UserError(f"{where}: image_id {img!r} is no frame of this dataset (1..{frames_in_data}, as "
                            "hydrabench export coco numbers them): a file for another dataset?")
        cat = r.get("category_id")
        if not isinstance(cat, int) or not 1 <= cat <= len(CLASSES):
            raise UserError(f"{where}: category_id {cat!r} is not in the class table (1..{len(CLASSES)}: "
                            f"{', '.join(CLASSES)})")
        if not _finite(r.get("bbox"), 4) or min(r["bbox"][2:]) < 0:
            raise UserError(f"{where}: bbox must be [x, y, w, h], finite, w and h >= 0, got {r.get('bbox')!r}")
        if not _finite([r.get("score")], 1) or r["score"] < 0:
            raise UserError(f"{where}: score must be a finite number >= 0, got {r.get('score')!r}")
        if img - 1 in rows:
            x, y, w, h = r["bbox"]
            rows[img - 1][0].append([x, y, x + w, y + h])
            rows[img - 1][1].append(float(r["score"]))
            rows[img - 1][2].append(cat)
    return {f: Detections(np.array(b, float).reshape(-1, 4), np.array(s, float), np.array(lab, np.int64))
            for f, (b, s, lab) in rows.items()}


def named_file(spec: str) -> tuple[str | None, Path]:
    """`[NAME=]FILE` -> (NAME or None, FILE)."""
    name, sep, path = spec.partition("=")
    if sep and name and "/" not in name:
        return name, Path(path)
    return None, Path(spec)


def merge_labels(labels: dict) -> dict:
    """A frame's labels with van -> car and group_of_pedestrians -> pedestrian (`MERGED`)."""
    from sim.actors import CLASSES

    ids = {CLASSES.index(a) + 1: CLASSES.index(b) + 1 for a, b in MERGED.items()}
    out = dict(labels)
    for key, lab in labels.items():
        if isinstance(lab, dict) and "labels" in lab:
            out[key] = {**lab, "labels": [ids.get(int(v), int(v)) for v in lab["labels"]]}
    return out


class MergedReader:
    """A DatasetReader whose labels are in the merged classes (what nuScenes detection names tell)."""

    def __init__(self, reader):
        self._reader = reader

    def labels(self, i: int) -> dict:
        return merge_labels(self._reader.labels(i))

    def __getattr__(self, name):
        return getattr(self._reader, name)


def merge_detections(d):
    from fusion.late import Detections
    from sim.actors import CLASSES

    lab = d.labels.copy()
    for a, b in MERGED.items():
        lab[lab == CLASSES.index(a) + 1] = CLASSES.index(b) + 1
    return Detections(d.boxes, d.scores, lab)


def load_external(reader, split: str = "all", *, nuscenes=(), coco=(), export=None,
                  missing: str = "refuse") -> tuple[ExternalSet, ExportIndex | None]:
    """The detections of the files `nuscenes` and `coco` ([NAME=]FILE each) on the frames of `split`
    (`split_frames`) of `reader`, and the export's index (None without `export`)."""
    if missing not in MISSING:
        raise UserError(f"--missing must be one of {', '.join(MISSING)}, got {missing!r}")
    if split != "all" and export is None:
        raise UserError(f"--split {split}: splits are the export's (splits.json): give --export DIR")
    if not nuscenes and not coco:
        raise UserError("give at least one detection file (--nuscenes or --coco)")
    if nuscenes and export is None:
        raise UserError("--nuscenes needs --export DIR: the nuScenes export of DATA its sample tokens refer to")
    index = ExportIndex(export, reader) if export is not None else None
    metas = {f: dict(reader.meta(f), dataset_index=f) for f in split_frames(index, reader, split)}
    if not metas:
        raise UserError(f"--split {split}: no frames")
    per_branch, sensors, sources, left_out = {}, {}, {}, {}
    for spec in nuscenes:
        name, path = named_file(spec)
        dets, used, left = read_nuscenes(path, index, metas, missing)
        name = name or "+".join(s.split("_")[0] for s in used)
        if name in per_branch:
            raise UserError(f"--nuscenes {spec}: a second file for branch {name!r} (name them: NAME=FILE)")
        per_branch[name], sensors[name], sources[name] = dets, used, str(path)
        if left:
            left_out[name] = len(left)
    coco_names = set()
    for spec in coco:
        name, path = named_file(spec)
        name = name or "camera"
        coco_names.add(name)
        if name in per_branch:
            raise UserError(f"--coco {spec}: a second file for branch {name!r} (name them: NAME=FILE)")
        per_branch[name], sensors[name], sources[name] = read_coco(path, metas, len(reader)), ("camera_right",), str(path)
    merged = bool(nuscenes)
    per_frame = []
    for f in sorted(metas):
        per = {b: (merge_detections(d[f]) if merged else d[f]) for b, d in per_branch.items()}
        per_frame.append((metas[f], per))
    files = {b: sources[b] for b in sources if b not in coco_names}
    return ExternalSet(per_frame, sensors, sources, merged, left_out, files), index


def read_selection(path, ext: ExternalSet, index: ExportIndex | None) -> list[tuple[str, ...]]:
    """Per scored frame, the branches a selection file chooses (keys: frame index or sample token), in
    branch order (a selection is a set: `study.experiments.gate_protocol.branch_set`)."""
    from study.experiments.gate_protocol import branch_set

    path = Path(path)
    doc = load_json(path, "selection")
    if not isinstance(doc, dict):
        raise UserError(f"{path}: a selection file is a JSON object: frame index or sample token -> [branch, ...]")
    chosen = {}
    for key, value in doc.items():
        if index is not None and key in index.frame_of:
            frame = index.frame_of[key]
        elif key.isdigit():
            frame = int(key)
        else:
            raise UserError(f"{path}: key {key!r} is neither a frame index nor a sample token of the export")
        if frame in chosen:
            raise UserError(f"{path}: frame {frame} is chosen for twice (key {key!r})")
        if not isinstance(value, list):
            raise UserError(f"{path}: [{key!r}]: not a list of branch names")
        chosen[frame] = branch_set(value, ext.branches, f"{path}: [{key!r}]", allow_empty=True)
    frames = [m["dataset_index"] for m, _ in ext.per_frame]
    left = [f for f in frames if f not in chosen]
    if left:
        raise UserError(f"{path}: chooses nothing for {len(left)} of the {len(frames)} scored frames (first: frame "
                        f"{left[0]}); an empty list chooses no branch")
    return [chosen[f] for f in frames]


ORACLE_FIXED = "; scored here with its choice held fixed in every draw, so its interval is optimistic too"


def context_oracle(ext: ExternalSet, chosen: dict, scores: dict, resamples: int, reader, protocol, sources) -> dict | None:
    """The context oracle of the fixed configurations (each branch alone, late fusion, all branches):
    per context the one of best mAP on the scored frames (a bound, chosen on test; ties: the first), its
    per-frame selection, and the room for context without its optimism (`study.experiments.bounds.corrected_room`:
    split-sample and naive, each beside its null), over all_branches (late fusion where there is no
    all_branches). None with fewer than two configurations."""
    from study.experiments.bounds import StudyMatches, corrected_room

    fixed = [k for k in chosen if k.startswith("single:") or k in ("late", "all_branches")]
    if len(fixed) < 2:
        return None
    contexts = sorted({m["context"] for m, _ in ext.per_frame})

    def value(k, c):
        v = scores[k]["map_per_context"].get(c)
        return -np.inf if v is None or not np.isfinite(v) else v

    pick = {c: max(fixed, key=lambda k, c=c: value(k, c)) for c in contexts}  # max keeps the first of ties
    selection = [chosen[pick[m["context"]]][i] for i, (m, _) in enumerate(ext.per_frame)]
    reference = "all_branches" if "all_branches" in fixed else "late" if "late" in fixed else fixed[0]
    room = None
    if resamples:
        sm = StudyMatches.of({k: sources[k] for k in fixed}, {k: tuple(chosen[k][0]) for k in fixed}, {}, reader,
                             protocol)
        room = corrected_room(sm, resamples, reference=reference)
    return {"selection": selection, "choice": pick, "candidates": fixed, "chosen_on": "the scored frames (a bound)",
            "room_corrected": room}


def score_external(reader, ext: ExternalSet, *, selections=None, gates=None, fusion: str = "soft-nms",
                   resamples: int = 500, protocol: str = "reference", interval: str = "sequence") -> dict:
    """Each branch alone, `late` (the single-sensor branches fused), `all_branches` (every branch
    fused, when some use several sensors), each selection file's choice (`selections`: name ->
    per-frame tuples) and each gate from outside's (`gates`: name -> per-frame tuples, made by
    `study.experiments.gate_protocol.gate_selection`), scored as `hydrabench compare` scores the own networks:
    VOC mAP@0.5 in the right camera under `protocol`, per context and per severity, and the paired
    sequence bootstrap's intervals of every method and of its difference with late fusion, overall and
    per context. Each method also carries the branches it fuses per frame and the sensors' energy
    (EcoFusion Eq. 10-11 per fused frame with clock gating, `fusion.eco.energy.total_energy` with no
    compute energy: what running a detector from outside costs is not known here)."""
    from fusion.eco.energy import total_energy
    from study.engine.scoring import (
        context_bootstrap,
        difference_interval,
        fuse_selection,
        fusion_method,
        score,
    )
    from study.experiments.bounds import CONTEXT_ORACLE, CONTEXT_ORACLE_LABEL
    from study.experiments.compare import map_difference, verdict
    from study.numbers import rounded

    method = fusion_method(fusion)
    rdr = MergedReader(reader) if ext.merged else reader
    n = len(ext.per_frame)
    frames = {b: "camera_right" for b in ext.branches}
    singles = [b for b in ext.branches if len(ext.branch_sensors[b]) == 1]
    kinds = {f"single:{b}": f"{'+'.join(ext.branch_sensors[b])} alone" for b in ext.branches}
    chosen = {f"single:{b}": [(b,)] * n for b in ext.branches}
    if len(singles) > 1:
        kinds["late"], chosen["late"] = "late fusion of the single-sensor branches", [tuple(singles)] * n
    if len(ext.branches) > max(len(singles), 1) and len(ext.branches) > 1:
        kinds["all_branches"], chosen["all_branches"] = "every branch fused", [tuple(ext.branches)] * n
    for name, sel in (selections or {}).items():
        kinds[f"selection:{name}"], chosen[f"selection:{name}"] = "per-frame selection from a file", sel
    for name, sel in (gates or {}).items():
        kinds[f"gate:{name}"], chosen[f"gate:{name}"] = "gate from outside (study.experiments.gate_protocol)", sel
    sources = {k: fuse_selection(ext.per_frame, sel, frames, method) for k, sel in chosen.items()}
    scores = {k: score(s, rdr, "camera_right", protocol=protocol) for k, s in sources.items()}
    oracle = context_oracle(ext, chosen, scores, resamples, rdr, protocol, sources)
    if oracle:
        chosen[CONTEXT_ORACLE], kinds[CONTEXT_ORACLE] = oracle.pop("selection"), CONTEXT_ORACLE_LABEL + ORACLE_FIXED
        sources[CONTEXT_ORACLE] = fuse_selection(ext.per_frame, chosen[CONTEXT_ORACLE], frames, method)
        scores[CONTEXT_ORACLE] = score(sources[CONTEXT_ORACLE], rdr, "camera_right", protocol=protocol)
    boot = (context_bootstrap(sources, rdr, "camera_right", protocol=protocol, resamples=resamples, classes="all",
                              desc="bootstrap the methods", design=interval) if resamples else None)
    ref = "late" if "late" in scores else None
    contexts = sorted({m["context"] for m, _ in ext.per_frame})
    methods = {}

    def sensor_energy(choice) -> float:
        return total_energy(0.0, sorted({s for b in choice for s in ext.branch_sensors[b]}))

    for k in chosen:
        sc = scores[k]
        row = {"kind": kinds[k], "map": sc["map"], "map_vehicles": sc["map_vehicles"],
               "map_per_context": sc["map_per_context"], "map_vehicles_per_severity": sc["map_vehicles_per_severity"],
               "ap_per_class": sc["ap_per_class"], "positives_per_class": sc["positives_per_class"],
               "branches_per_frame": rounded(np.mean([len(c) for c in chosen[k]])),
               "sensor_energy_j": rounded(np.mean([sensor_energy(c) for c in chosen[k]]))}
        if k.startswith(("selection:", "gate:")):
            row["branch_share"] = {b: rounded(np.mean([b in c for c in chosen[k]])) for b in ext.branches}
        if boot:
            row["ci95"] = boot["per_context"]["all"]["map"][k]
            row["ci95_per_context"] = {c: boot["per_context"][c]["map"][k] for c in contexts}
            if ref and k != ref:
                iv = difference_interval(boot["per_context"]["all"], k, ref)
                row["minus_late"] = {"value": map_difference(sc["map"], scores[ref]["map"]), "ci95": iv, "verdict": verdict(iv)}
                row["minus_late_per_context"] = {
                    c: {"ci95": (ivc := difference_interval(boot["per_context"][c], k, ref)), "verdict": verdict(ivc)}
                    for c in contexts}
        methods[k] = row
    return {"frames": n, "contexts": contexts, "fusion": fusion, "protocol": protocol, "branches": ext.branches,
            "branch_sensors": {b: list(s) for b, s in ext.branch_sensors.items()}, "sources": ext.sources,
            "classes": "merged (van -> car, group_of_pedestrians -> pedestrian)" if ext.merged else "RADIATE (8)",
            "left_out_frames_scored_empty": ext.left_out, "methods": methods, "context_oracle": oracle,
            "not_available": {"deep, attention": "learned gates read the own networks' stem features",
                              "optimal": "reads each branch's Faster R-CNN losses, which external detections lack"},
            "bootstrap": {"resamples": resamples, "unit": "sequence", "design": interval} if boot else None,
            "energy": "sensor_energy_j: the rig's sensors per fused frame at 4 Hz, those a method does not read "
                      "clock-gated (EcoFusion Eq. 10-11, fusion.eco.energy); no compute energy (unknown for "
                      "detectors from outside)",
            "metric": "VOC all-point AP at IoU 0.5, every class with ground truth, right camera"}


def bev_results(per_frame: list, branch: str, index: ExportIndex, sensors) -> dict:
    """A BEV branch's detections ([(meta, {branch: Detections in BEV pixels})]) as nuScenes results:
    each box the 3D box HydraFusion's Appendix A makes of it (`sensors.rig.bev_boxes_to_camera`: the
    BEV rectangle from the road up to the class's average height), in the log's global frame, at full
    precision. How the own networks' detections leave hydrabench for the devkit's tools."""
    from sensors.export.nuscenes import CLASS_TABLE
    from sensors.rig import Calibration, class_height
    from sim.actors import CLASSES

    results = {index.token_of[int(m["dataset_index"])]: [] for m, _ in per_frame}
    for meta, per in per_frame:
        frame = int(meta["dataset_index"])
        token = index.token_of[frame]
        calib = Calibration.from_dict(meta["calibration"])
        global_from_ego = np.asarray(meta["ego_pose"], float).copy()
        global_from_ego[:3, 3] += index.offset[frame]
        global_from_radar = global_from_ego @ np.asarray(calib.ego_from_radar, float)
        d = per[branch]
        for box, s, lab in zip(d.boxes, d.scores, d.labels):
            c = calib.bev_to_radar(np.array([[box[0], box[1]], [box[2], box[1]], [box[2], box[3]], [box[0], box[3]]]))
            along, across = c[1] - c[0], c[3] - c[0]
            yaw = math.atan2(along[1], along[0])
            h = class_height(int(lab))
            center = np.r_[c.mean(axis=0), -calib.radar_height_m + h / 2, 1.0]
            rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
            cls = CLASSES[int(lab) - 1]
            results[token].append({
                "sample_token": token, "translation": [float(v) for v in (global_from_radar @ center)[:3]],
                "size": [float(np.linalg.norm(across)), float(np.linalg.norm(along)), h],
                "rotation": [float(v) for v in _matrix_quaternion(global_from_radar[:3, :3] @ rz)],
                "velocity": [0.0, 0.0], "detection_name": CLASS_TABLE[cls][1], "detection_score": float(s),
                "attribute_name": ""})
    flags = {k: s in sensors for k, s in SENSOR_FLAGS}
    return {"meta": {**flags, "use_map": False, "use_external": False}, "results": results}


def _matrix_quaternion(R) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, unrounded (the export rounds to 9 digits)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, float)).as_quat()
    return np.array([w, x, y, z])


def coco_results(per_frame: list, branch: str) -> list:
    """A right-camera branch's detections as COCO results (`hydrabench export coco`'s numbering)."""
    out = []
    for meta, per in per_frame:
        d = per[branch]
        for (x1, y1, x2, y2), s, lab in zip(d.boxes, d.scores, d.labels):
            out.append({"image_id": int(meta["dataset_index"]) + 1, "category_id": int(lab),
                        "bbox": [float(x1), float(y1), float(x2 - x1), float(y2 - y1)], "score": float(s)})
    return out
