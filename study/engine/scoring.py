"""Running a trained HydraFusion on dataset frames: load a run, batch frames, collect detections,
fuse them in the reference frame and score them (VOC mAP@0.5, difficult boxes ignored)."""

from __future__ import annotations

import json
import weakref
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from fusion.data import FrameDataset, collate, hold_out_sequences, split_by_sequence
from fusion.intervals import map_draws, map_intervals
from fusion.late import Detections, fuse
from fusion.metrics import DrawScorer, ImageMatches, evaluate_detections
from fusion.robustness import twin_relative_accuracy
from sensors.dataset import DatasetReader
from sensors.rig import Calibration
from sim.actors import CLASSES
from sim.errors import UserError
from study.numbers import rounded, rounded_interval


def fusion_method(name: str) -> str:
    """`fusion.boxes.method_name` (the registry's name of a late-fusion method, given by name or label),
    a UserError for an unknown one."""
    from fusion.boxes import method_name

    try:
        return method_name(name)
    except ValueError as e:
        raise UserError(str(e)) from None


def load_run(run: str | Path, which: str = "latest", device: str = "cpu"):
    """(model in eval mode on `device`, run config dict) from a training run directory."""
    from fusion.nets import build_hydrafusion
    from fusion.nets.profile import BranchSpec
    from study.engine.run_config import run_profile

    run = Path(run)
    cfg_path = run / "config.json"
    ckpt = run / ("checkpoint.pt" if which == "latest" else f"{which}.pt")
    if not cfg_path.exists():
        raise UserError(f"{run} is not a training run (no config.json; see hydrabench train)")
    if not ckpt.exists():  # a run, without the checkpoint asked for: say which it has
        epochs = sorted(p.stem for p in run.glob("epoch-*.pt"))
        has = f"its epochs: {', '.join(epochs)}" if epochs else "it has no epoch-NNN.pt yet"
        raise UserError(f"{ckpt} does not exist: the run has no {'checkpoint.pt' if which == 'latest' else which} "
                        f"({has}; --checkpoint latest is checkpoint.pt)")
    cfg = json.loads(cfg_path.read_text())
    branches = [BranchSpec(b["name"], tuple(b["sensors"]), b["frame"], b.get("fusion", "features"))
                for b in cfg["branch_specs"]]
    from fusion.nets.uninitialised import uninitialised

    with uninitialised():  # every weight is loaded strictly below: drawing them first is wasted time
        model = build_hydrafusion(profile=run_profile(cfg, run), branches=branches)
    from study.engine.checkpoints import load_checkpoint, load_weights

    load_weights(model, load_checkpoint(ckpt)["model"], ckpt)
    model.eval()
    if str(device) != "cpu":
        model.to(device)
    return model, cfg


def run_train_test(run_cfg: dict, data: str | Path, who: str) -> tuple[list[int], list[int]]:
    """(train, test) frames of the run's own split of `data`, which must be the run's training dataset
    (a gate trains on the train split and is tested on the test split). UserError naming `who` (the
    command) otherwise, or when either split is empty."""
    from sensors.dataset import DatasetReader
    from sim.errors import UserError

    if not is_runs_data(run_cfg, DatasetReader(data).manifest):
        raise UserError(f"{who} needs the run's training dataset ({run_cfg.get('data')}), not {data}: gates train "
                        "on the run's train split and are tested on its test split")
    train, _ = frames_for(run_cfg, data, "train")
    test, _ = frames_for(run_cfg, data, "test")
    if not train or not test:
        raise UserError(f"the run's split of {data} has {len(train)} train and {len(test)} test frames; {who} "
                        "needs both")
    return train, test


def frames_for(run_cfg: dict, data: str | Path, split: str = "auto") -> tuple[list[int], str]:
    """Which frames of `data` to evaluate: the run's test split when `data` is its training dataset
    (same generation config), every frame otherwise; `split` = "test" | "train" | "gate" | "all"
    forces it. "train" is the frames the detectors trained on; "gate" the run's gate split
    (`TrainConfig.gate_holdout`: training sequences the detectors never saw; empty without one).
    "data-test": `data`'s own by-sequence test split with the run's split settings, on any dataset
    (the frames a run trained on `data` is tested on: two runs compared on the same frames)."""
    if split not in ("auto", "test", "train", "gate", "all", "data-test"):
        raise UserError(f"unknown split {split!r} (choose from: auto, test, train, gate, all, data-test)")
    reader = DatasetReader(data)
    if split == "data-test":
        return split_by_sequence(reader, run_cfg["train_fraction"], run_cfg["split_seed"])[1], split
    if "parts" in reader.manifest and split != "all":
        return view_frames(run_cfg, reader, split), split
    same = reader.manifest["config"] == run_cfg.get("data_config")
    if split == "auto":
        split = "test" if same else "all"
    if split == "all":
        return list(range(len(reader))), "all"
    if not same:
        raise UserError(f"--split {split} needs the run's training dataset ({run_cfg.get('data')})")
    train, test = split_by_sequence(reader, run_cfg["train_fraction"], run_cfg["split_seed"])
    if split == "test":
        return test, split
    train, gate = hold_out_sequences(reader, train, run_cfg.get("gate_holdout", 0.0), run_cfg["split_seed"])
    return (train if split == "train" else gate), split


VIEW_PARTS = ("detectors", "gate", "test")
"""The parts of a study's dataset view (`sensors.combine`): the detectors' own dataset, then the gate
set and the test set, each generated with its own seed and size."""


def view_frames(run_cfg: dict, reader: DatasetReader, split: str) -> list[int]:
    """A split of a dataset view: "gate" and "test" (and "auto": test) every frame of those parts, or,
    for a view without that part, the run's own gate or test split of the "detectors" part; "train"
    the run's train split of the "detectors" part (which must be the run's training dataset). Indices
    are the view's."""
    from sensors.combine import part_indices

    parts = reader.manifest["parts"]
    split = "test" if split == "auto" else split
    if split in ("gate", "test") and split in parts:
        return part_indices(reader.manifest, split)
    det = parts.get("detectors")
    if det is None or det["config"] != run_cfg.get("data_config"):
        raise UserError(f"{reader.root}: its 'detectors' part is not the run's training dataset ({run_cfg.get('data')})")
    own = DatasetReader((reader.root / reader.index[det["start"]][0]).resolve().parent)
    train, test = split_by_sequence(own, run_cfg["train_fraction"], run_cfg["split_seed"])
    train, gate = hold_out_sequences(own, train, run_cfg.get("gate_holdout", 0.0), run_cfg["split_seed"])
    return [det["start"] + i for i in {"train": train, "gate": gate, "test": test}[split]]


def is_runs_data(run_cfg: dict, manifest: dict) -> bool:
    """Whether a dataset (its manifest) is the run's training dataset, or a view whose "detectors"
    part is."""
    if "parts" in manifest:
        det = manifest["parts"].get("detectors")
        return det is not None and det["config"] == run_cfg.get("data_config")
    return manifest["config"] == run_cfg.get("data_config")


def to_detections(d: dict) -> Detections:
    return Detections(d["boxes"].detach().float().cpu().numpy().astype(np.float64),
                      d["scores"].detach().float().cpu().numpy().astype(np.float64),
                      d["labels"].detach().cpu().numpy().astype(np.int64))


def run_branches(model, data, indices, branches, batch_size: int = 4, progress: str = "detect",
                 sensors=None, clear: bool = False, workers: int = 0, amp: bool = False):
    """Per-frame detections of each branch in its own frame: list of (meta, {branch: Detections});
    `clear` runs on the clear-weather twins of the frames (datasets generated with --twins).
    The model runs where its parameters are (`study.engine.device`), with bf16 autocast when `amp`;
    `workers` DataLoader processes decode the frames."""
    from study.engine.device import DeviceSetup, to_device

    need = sensors or model.sensors_for(list(branches))
    device = next(model.parameters()).device
    ds = FrameDataset(data, indices, sensors=need, clear=clear, bev_size=model.transform.image_size("radar"),
                      uint8=device.type == "cuda")  # uint8 to a GPU, float32 there (`to_device`)
    loader = DataLoader(ds, batch_size=batch_size, shuffle=False, collate_fn=collate, num_workers=workers,
                        pin_memory=device.type == "cuda")
    autocast = DeviceSetup(str(device), 0, bool(amp)).autocast
    from sim.progress import progress as progress_bar

    out = []
    # a bar on a terminal, a line every few seconds in a log (sim.progress)
    with torch.no_grad(), progress_bar(total=len(ds), desc=progress, unit="frame") as bar:
        for inputs, _targets, metas in loader:
            inputs, _ = to_device(inputs, None, device)
            with autocast():
                dets = model(inputs, selection=list(branches))
            for meta, per in zip(metas, dets):
                out.append((meta, {n: to_detections(d) for n, d in per.items()}))
            bar.update(len(metas))
    return out


def ground_truth(labels: dict, frame: str, bev_crop: tuple | None = None, meta: dict | None = None,
                 protocol=None) -> dict:
    """Ground truth of one frame in `frame` under the evaluation `protocol` (fusion.protocol; None =
    the stored labels, i.e. `visible`; the others need the frame's `meta`); `bev_crop` = ((H, W),
    full size) of the BEV crop a model sees."""
    if protocol is not None:
        from fusion.protocol import frame_labels

        labels = frame_labels(labels, meta, protocol)
    lab = labels[frame]
    if frame == "bev" and bev_crop is not None:
        from fusion.data import crop_bev_labels

        lab = crop_bev_labels(lab, bev_crop[0], bev_crop[1])
    gt = {"boxes": np.array(lab["boxes"], float).reshape(-1, 4), "labels": np.array(lab["labels"], np.int64),
          "difficult": np.array(lab["difficult"], bool)}
    if "distance_m" in lab:
        gt["distance_m"] = np.array(lab["distance_m"], float)
    return gt


# Ground truth per reader, frame index, view, crop and protocol: every method scored on a dataset
# reads the same boxes, and projecting each frame's 3D boxes again per method was half of `score`'s
# time (10 methods x 192 frames in `compare`). Keyed by the reader's id; its entries are dropped
# when the reader is collected (so a new reader at a reused id never reads an old one's boxes).
_GROUND_TRUTH: dict[int, dict] = {}


def frame_ground_truth(reader: DatasetReader, meta: dict, frame: str, bev_crop: tuple | None = None,
                       protocol=None) -> dict:
    """`ground_truth` of the frame `meta["dataset_index"]` of `reader`, computed once per reader and
    arguments; the arrays are read-only (they are shared by every caller)."""
    from fusion.protocol import as_protocol

    key = (meta["dataset_index"], frame, repr(bev_crop), json.dumps(as_protocol(protocol).describe(), sort_keys=True))
    if id(reader) not in _GROUND_TRUTH:
        _GROUND_TRUTH[id(reader)] = {}
        weakref.finalize(reader, _GROUND_TRUTH.pop, id(reader), None)
    per_reader = _GROUND_TRUTH[id(reader)]
    if key not in per_reader:
        gt = ground_truth(reader.labels(meta["dataset_index"]), frame, bev_crop, meta, protocol)
        for v in gt.values():
            v.flags.writeable = False
        per_reader[key] = gt
    return per_reader[key]


def _above(d: Detections, threshold: float) -> dict:
    """The detections scoring >= threshold, as evaluate_detections takes them."""
    keep = d.scores >= threshold
    return {"boxes": d.boxes[keep], "scores": d.scores[keep], "labels": d.labels[keep]}


# The learning check's vehicle classes (HydraFusion's car, van, truck, bus).
VEHICLES = ("car", "van", "truck", "bus")


def matched_ranges(d: dict, g: dict, meta: dict, frame: str) -> np.ndarray:
    """The range (m) `in_range_bin` places each detection of one frame at: a detection that overlaps
    a ground-truth box of its class at IoU >= 0.5 takes that object's range (its best match); any
    other detection, a false positive, its own estimated range (fusion.protocol.detection_ranges)."""
    from fusion.metrics import box_iou
    from fusion.protocol import detection_ranges

    boxes = np.asarray(d["boxes"], float).reshape(-1, 4)
    r = detection_ranges(boxes, frame, meta["calibration"])
    if len(boxes) and len(g["boxes"]):
        iou = box_iou(boxes, g["boxes"])
        iou[np.asarray(d["labels"])[:, None] != g["labels"][None, :]] = 0.0
        best = iou.argmax(axis=1)
        hit = iou[np.arange(len(boxes)), best] >= 0.5
        r = np.where(hit, g["distance_m"][best], r)
    return r


def in_range_bin(dets: list, gts: list, metas: list, frame: str, lo: float, hi: float,
                 ranges: list | None = None) -> tuple[list, list]:
    """Detections and ground truth of one range bin [lo, hi) m: ground truth outside the bin becomes
    difficult (ignored: a detection matching it is neither true nor false). Each detection is placed
    at its `matched_ranges` (given in `ranges`, one array per frame, or computed here); detections
    placed outside the bin are dropped."""
    out_d, out_g = [], []
    for j, (d, g, meta) in enumerate(zip(dets, gts, metas)):
        r = matched_ranges(d, g, meta, frame) if ranges is None else ranges[j]
        keep = (r >= lo) & (r < hi)
        out_d.append({k: np.asarray(v)[keep] for k, v in d.items()})
        dist = g["distance_m"]
        out_g.append({**g, "difficult": g["difficult"] | ~((dist >= lo) & (dist < hi))})
    return out_d, out_g


def score(per_frame: list, reader: DatasetReader, frame: str = "camera_right", bev_crop: tuple | None = None,
          protocol=None) -> dict:
    """VOC mAP@0.5 of detections already in `frame` under the evaluation `protocol`: overall, per
    class, per context; and the mean over the vehicle classes (VEHICLES) overall, per context, per
    weather severity ("map_vehicles*"; severity 0 is clear weather), per range bin of the objects'
    range from the radar (fusion.protocol.RANGE_BINS; `in_range_bin`) and per context and range bin."""
    from fusion.protocol import RANGE_BINS, as_protocol, range_bin_names

    dets, gts, contexts, severities, metas = [], [], [], [], []
    for meta, d in per_frame:
        gts.append(frame_ground_truth(reader, meta, frame, bev_crop, protocol))
        dets.append({"boxes": d.boxes, "scores": d.scores, "labels": d.labels})
        contexts.append(meta["context"])
        severities.append(str(meta.get("severity", 0)))
        metas.append(meta)
    res = evaluate_detections(dets, gts, classes=range(1, len(CLASSES) + 1))
    vehicles = [CLASSES.index(c) + 1 for c in VEHICLES]
    bins = list(zip(range_bin_names(), RANGE_BINS[:-1], RANGE_BINS[1:]))
    has_range = all("distance_m" in g for g in gts)

    # each detection's range once per frame: every bin, overall and per context, reads it
    ranges = [matched_ranges(d, g, m, frame) for d, g, m in zip(dets, gts, metas)] if has_range else []

    def per_range(ks) -> dict:
        if not has_range:
            return {}
        out = {}
        for name, lo, hi in bins:
            d_b, g_b = in_range_bin([dets[k] for k in ks], [gts[k] for k in ks], [metas[k] for k in ks], frame, lo, hi,
                                    ranges=[ranges[k] for k in ks])
            out[name] = _mean_of(evaluate_detections(d_b, g_b, classes=vehicles), vehicles)
        return out

    def per_group(groups) -> dict:
        by = defaultdict(list)
        for k, c in enumerate(groups):
            by[c].append(k)
        return {c: evaluate_detections([dets[k] for k in ks], [gts[k] for k in ks], classes=range(1, len(CLASSES) + 1))
                for c, ks in sorted(by.items())}

    by_ctx, by_sev = per_group(contexts), per_group(severities)
    per_ctx = {c: rounded(r.mean_ap) for c, r in by_ctx.items()}
    veh_ctx = {c: _mean_of(r, vehicles) for c, r in by_ctx.items()}
    veh_sev = {c: _mean_of(r, vehicles) for c, r in by_sev.items()}
    ctx_frames = defaultdict(list)
    for k, c in enumerate(contexts):
        ctx_frames[c].append(k)
    return {
        "protocol": as_protocol(protocol).describe(),
        "map": rounded(res.mean_ap),
        "map_vehicles": _mean_of(res, vehicles),
        "map_vehicles_per_context": veh_ctx,
        "map_vehicles_per_severity": veh_sev,
        "map_vehicles_per_range": per_range(range(len(dets))),
        "map_vehicles_per_context_range": {c: per_range(ks) for c, ks in sorted(ctx_frames.items())},
        "ap_per_class": {CLASSES[c - 1]: rounded(v) for c, v in res.ap.items()},
        "map_per_context": per_ctx,
        "positives_per_class": {CLASSES[c - 1]: int(n) for c, n in res.n_positives.items()},
        "frames": len(per_frame),
    }


def operating_point(per_frame: list, reader: DatasetReader, frame: str = "camera_right",
                    bev_crop: tuple | None = None, threshold: float = 0.5, protocol=None) -> dict:
    """Recall and precision of the vehicle classes (VEHICLES) at one score threshold, overall and
    per weather severity: what a user of the detector would see, where mAP averages over all
    thresholds. VOC matching (same class, IoU >= 0.5, one detection per box, difficult boxes
    ignored). {"threshold", "recall", "precision", "per_severity": {severity: {recall, precision}}}."""
    vehicles = [CLASSES.index(c) + 1 for c in VEHICLES]
    groups = defaultdict(list)
    for meta, d in per_frame:
        gt = ground_truth(reader.labels(meta["dataset_index"]), frame, bev_crop, meta, protocol)
        groups[str(meta.get("severity", 0))].append((_above(d, threshold), gt))

    def point(pairs) -> dict:
        r = evaluate_detections([a for a, _ in pairs], [b for _, b in pairs], classes=vehicles)
        tp = sum(r.n_true_positives.values())
        judged = sum(len(r.precision[c]) for c in vehicles)  # detections not matched to a difficult box
        pos = sum(r.n_positives.values())
        return {"recall": rounded(tp / pos) if pos else None, "precision": rounded(tp / judged) if judged else None,
                "positives": int(pos), "detections": int(judged)}

    everything = [x for v in groups.values() for x in v]
    return {"threshold": threshold, **point(everything),
            "per_severity": {k: point(groups[k]) for k in sorted(groups, key=int)}}


# Bins of an object's distance over the frame's visibility (MOR): Koschmieder's law leaves an object
# exp(-ln(20) d / MOR) of its contrast, i.e. 100-47 %, 47-22 %, 22-5 % and under 5 % in these bins.
VISIBILITY_BINS = (0.0, 0.25, 0.5, 1.0, float("inf"))


def bev_distances(lab: dict, calibration: dict) -> np.ndarray:
    """(N,) range [m] of each BEV label box's centre from the radar (Appendix A grid; the camera
    labels carry their own `distance_m`, from the camera)."""
    centres = np.array(lab["boxes"], float).reshape(-1, 4) @ np.array([[.5, 0], [0, .5], [.5, 0], [0, .5]])
    xy = Calibration.from_dict(calibration).bev_to_radar(centres)
    return np.hypot(xy[:, 0], xy[:, 1])


def recall_by_visibility(per_frame: list, reader: DatasetReader, frame: str = "camera_right",
                         bev_crop: tuple | None = None, threshold: float = 0.5, visibility: dict | None = None,
                         edges=VISIBILITY_BINS, protocol=None) -> dict:
    """Recall of the vehicle classes at one score threshold, binned by each object's distance over
    the frame's visibility d / MOR: where the camera's physics says an object fades (Koschmieder
    contrast exp(-ln(20) d / MOR)), does the detector lose it? Matching as VOC (same class, each
    detection to its best-IoU box, IoU >= 0.5, one detection per box, difficult boxes ignored), so
    the bins add up to `operating_point`'s recall.

    `visibility`: {dataset_index: MOR [m]} to bin by (for clear-weather twins: the degraded frame's
    MOR); default: each frame's own `meta["weather"]["visibility_m"]`.
    Returns {"<lo>-<hi>": {"objects", "found", "recall", "contrast": [at lo, at hi]}} in bin order.
    """
    from fusion.metrics import matched_ground_truth
    from sim.weather import LN20

    vehicles = [CLASSES.index(c) + 1 for c in VEHICLES]
    edges = np.asarray(edges, float)
    objects = np.zeros(len(edges) - 1, int)
    found = np.zeros(len(edges) - 1, int)
    for meta, d in per_frame:
        i = meta["dataset_index"]
        mor = float(visibility[i] if visibility is not None else meta["weather"]["visibility_m"])
        labels = reader.labels(i)
        if protocol is None and "distance_m" not in labels[frame]:
            lab = labels[frame]
            labels = {**labels, frame: {**lab, "distance_m": bev_distances(lab, meta["calibration"]).tolist()}}
        gt = ground_truth(labels, frame, bev_crop, meta, protocol)
        hit = matched_ground_truth([_above(d, threshold)], [gt], classes=vehicles)[0]
        ratio = gt["distance_m"] / mor
        counted = np.isin(gt["labels"], vehicles) & ~gt["difficult"]
        b = np.clip(np.searchsorted(edges, ratio, side="right") - 1, 0, len(edges) - 2)
        np.add.at(objects, b[counted], 1)
        np.add.at(found, b[counted & hit], 1)

    def name(lo, hi):
        return f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">={lo:g}"

    return {name(lo, hi): {"objects": int(n), "found": int(f), "recall": rounded(f / n) if n else None,
                           "contrast": [rounded(np.exp(-LN20 * lo)), rounded(np.exp(-LN20 * hi))]}
            for lo, hi, n, f in zip(edges[:-1], edges[1:], objects, found)}


def image_matches(frames: list, keys: list, gts: list, classes) -> ImageMatches:
    """`ImageMatches` of per-frame detections [(meta, Detections)], in the order of dataset `keys`."""
    by = {meta["dataset_index"]: d for meta, d in frames}
    return ImageMatches.of([{"boxes": by[k].boxes, "scores": by[k].scores, "labels": by[k].labels} for k in keys],
                           gts, classes=classes)


def _interval(values: np.ndarray) -> list | None:
    """[2.5th, 97.5th percentile] of the finite values (None when none is)."""
    v = values[np.isfinite(values)]
    return [rounded(np.percentile(v, 2.5)), rounded(np.percentile(v, 97.5))] if len(v) else None



def paired_bootstrap(deg_frames: list, clr_frames: list, reader, clear_reader, frame: str, bev_crop=None,
                     protocol=None, resamples: int = 200, seed: int = 0, severities=None,
                     desc: str = "bootstrap") -> dict:
    """95 % intervals of the vehicle mAP on degraded frames, on their clear twins, and of their ratio
    (MultiCorrupt's RA, here "retained"; `fusion.robustness.twin_relative_accuracy` draws and scores).

    Frames of one sequence share their traffic and weather, so whole sequences are drawn with
    replacement (a cluster bootstrap), and each draw is scored degraded and clear on the same
    frames (paired). `severities`: also per severity, resampling the sequences of each. Percentile
    intervals over `resamples` draws; the generator is seeded, so a rerun gives the same interval.
    """
    from sim.progress import progress as progress_bar

    vehicles = [CLASSES.index(c) + 1 for c in VEHICLES]

    keys = sorted(meta["dataset_index"] for meta, _ in deg_frames)
    if keys != sorted(meta["dataset_index"] for meta, _ in clr_frames):
        raise ValueError("paired_bootstrap: the degraded and clear frames differ")
    row = {k: j for j, k in enumerate(keys)}

    def matches(frames, rdr) -> ImageMatches:
        meta_of = {meta["dataset_index"]: meta for meta, _ in frames}
        gts = [ground_truth(rdr.labels(k), frame, bev_crop, meta_of[k], protocol) for k in keys]
        return image_matches(frames, keys, gts, vehicles)  # matched once; each draw only pools

    deg, clr = matches(deg_frames, reader), matches(clr_frames, clear_reader)
    seq_of = {meta["dataset_index"]: (meta["sequence_id"], str(meta.get("severity", 0))) for meta, _ in deg_frames}

    def interval(subset) -> dict:
        ks = sorted(subset)
        t = twin_relative_accuracy(lambda items: deg.mean_ap([row[ks[i]] for i in items]),
                                   lambda items: clr.mean_ap([row[ks[i]] for i in items]),
                                   [seq_of[k][0] for k in ks], resamples=resamples, seed=seed,
                                   on_draw=lambda: bar.update(1))
        return {"sequences": t.sequences, "degraded": rounded_interval(t.degraded_interval),
                "clear": rounded_interval(t.clear_interval), "retained": rounded_interval(t.interval)}

    present = [s for s in severities or () if any(seq_of[k][1] == s for k in keys)]
    with progress_bar(total=resamples * (1 + len(present)), desc=desc, unit="draw") as bar:
        out = {"resamples": int(resamples), "unit": "sequence", "seed": int(seed), "all": interval(keys)}
        if severities:
            out["per_severity"] = {s: interval([k for k in keys if seq_of[k][1] == s]) for s in present}
    return out


def context_bootstrap(sources: dict, reader, frame: str = "camera_right", protocol=None, resamples: int = 200,
                      seed: int = 0, desc: str = "bootstrap contexts", classes: str = "vehicles",
                      design: str = "sequence", scoring: str = "weighted") -> dict:
    """95 % intervals of each source's mAP (`classes`: "vehicles", the four vehicle classes, as
    `map_vehicles`; "all", every class, as `map`), overall and per context, and of the difference
    between every two sources, from draws of whole sequences with replacement (within each context;
    overall, from all sequences, by default). `sources`: name -> per-frame detections in `frame`, all on the
    same frames (e.g. each branch alone and the fused result). Each draw scores every source on the
    same frames, so a difference's interval is paired: one that excludes 0 says the order of the two
    would hold on another draw of sequences like these. Percentile intervals; seeded. `design`: how
    sequences are drawn (`fusion.intervals.design_draws`, strata: the contexts; "sequence", the
    default, draws from all of a group's sequences). `scoring`: how a draw is scored
    (`fusion.intervals.SCORINGS`: the same intervals either way, "weighted" ranks once). Per context
    (every group but "all"), the declared interval is jackknife-t over the context's sequences
    (`fusion.intervals.map_intervals`, "jackknife"; `hydrabench bench coverage`: the percentile interval
    of a few sequences' AP misses high), marked "interval": "jackknife-t".
    """
    from sim.progress import progress as progress_bar

    names = list(sources)
    if not names:
        raise ValueError("context_bootstrap: no sources")
    keys = sorted(meta["dataset_index"] for meta, _ in sources[names[0]])
    for n in names[1:]:
        if sorted(meta["dataset_index"] for meta, _ in sources[n]) != keys:
            raise ValueError(f"context_bootstrap: {n!r} was scored on other frames than {names[0]!r}")
    if classes not in ("vehicles", "all"):
        raise ValueError(f"context_bootstrap: classes must be 'vehicles' or 'all', got {classes!r}")
    class_ids = [CLASSES.index(c) + 1 for c in VEHICLES] if classes == "vehicles" else list(range(1, len(CLASSES) + 1))
    key = "map_vehicles" if classes == "vehicles" else "map"
    meta_of = {meta["dataset_index"]: meta for meta, _ in sources[names[0]]}
    gts = [frame_ground_truth(reader, meta_of[k], frame, None, protocol) for k in keys]
    matches = {n: image_matches(sources[n], keys, gts, class_ids) for n in names}
    row = {k: j for j, k in enumerate(keys)}
    groups = {"all": keys}
    for k in keys:
        groups.setdefault(meta_of[k]["context"], []).append(k)
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    scorers = {n: DrawScorer(m) for n, m in matches.items()} if scoring == "weighted" else None

    out = {"resamples": int(resamples), "unit": "sequence", "design": design, "seed": int(seed), "per_context": {}}
    with progress_bar(total=resamples * len(groups), desc=desc, unit="draw") as bar:
        for g, ks in groups.items():
            by: dict = {}
            for k in ks:
                by.setdefault(meta_of[k]["context"], {}).setdefault(meta_of[k]["sequence_id"], []).append(row[k])
            sequences = sum(len(v) for v in by.values())
            if g != "all" and sequences >= 2:  # the declared per-context interval: jackknife-t, no draws
                jk = map_intervals(matches, by, 1, seed, ("jackknife",), design, pairs, scorers)["intervals"]["jackknife"]
                out["per_context"][g] = {
                    "sequences": sequences, "interval": "jackknife-t",
                    key: {n: _rounded(jk[n]) for n in names},
                    "difference": {f"{a} - {b}": _rounded(jk[f"{a} - {b}"]) for a, b in pairs},
                }
                bar.update(resamples)
                continue
            draws = map_draws(matches, by, resamples, seed, design, scoring, scorers)
            bar.update(resamples)
            out["per_context"][g] = {
                "sequences": sequences,
                key: {n: _interval(draws[:, i]) for i, n in enumerate(names)},
                "difference": {f"{a} - {b}": _interval(draws[:, names.index(a)] - draws[:, names.index(b)])
                               for a, b in pairs},
            }
    return out


def _rounded(iv) -> list | None:
    return None if iv is None else [rounded(iv[0]), rounded(iv[1])]


def difference_interval(group: dict, name: str, ref: str) -> list | None:
    """The interval of `name` minus `ref` from one group of `context_bootstrap` (each pair is stored
    once, as "a - b" in the order the sources were given; the other order is its negation)."""
    d = group["difference"]
    if f"{name} - {ref}" in d:
        return d[f"{name} - {ref}"]
    iv = d.get(f"{ref} - {name}")
    return None if iv is None else [-iv[1], -iv[0]]


def _mean_of(res, classes) -> float | None:
    """Mean AP over those of `classes` that have ground truth (None when none has)."""
    aps = [res.ap[c] for c in classes if res.ap.get(c) is not None and not np.isnan(res.ap[c])]
    return rounded(float(np.mean(aps))) if aps else None



def fuse_selection(per_frame: list, selection, frames: dict, method: str, weights=None,
                   memo: dict | None = None) -> list:
    """The one way a gate's choice becomes scored boxes: [(meta, fused Detections in the right
    camera)] for [(meta, {branch: Detections})] and `selection` (per frame, the tuple of branch names
    to fuse; branches a frame lacks are left out). `memo`: a dict reused across calls of one method
    and one `per_frame`: each (frame position, tuple) is fused once, and each branch mapped to the
    right camera once (`fuse` of mapped detections is `fuse` of the originals: it maps first)."""
    from fusion.late import REFERENCE, to_reference

    memo = {} if memo is None else memo
    out = []
    for i, ((meta, per), frame_selection) in enumerate(zip(per_frame, selection, strict=True)):
        key = (i, tuple(frame_selection))
        if key not in memo:
            calib = Calibration.from_dict(meta["calibration"])
            for n in (n for n in frame_selection if n in per and ("reference", i, n) not in memo):
                memo["reference", i, n] = to_reference(per[n], frames[n], calib)
            mapped = {n: memo["reference", i, n] for n in frame_selection if n in per}
            memo[key] = fuse(mapped, dict.fromkeys(mapped, REFERENCE), calib, method=method, weights=weights)
        out.append((meta, memo[key]))
    return out


def fused(per_frame: list, branches, frames: dict, method: str, weights=None) -> list:
    """Late fusion of the same `branches` on every frame (`fuse_selection`)."""
    return fuse_selection(per_frame, [tuple(branches)] * len(per_frame), frames, method, weights)


def bev_crop_of(model, reader: DatasetReader) -> tuple:
    return (model.transform.image_size("radar"), int(reader.meta(0)["calibration"]["bev_size_px"]))


def native(per_frame: list, branch: str) -> list:
    return [(meta, per[branch]) for meta, per in per_frame if branch in per]
