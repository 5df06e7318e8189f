"""`hydrabench pem`: perception error models (`fusion.pem`) fitted on a model's stored predictions,
and predictions drawn from them in the same store as the networks' (`study.engine.predictions`), so that
`hydrabench compare MODEL DATA --predictions PRED` scores them with no network.

- `fit`: the model's predictions on a fitting dataset (made once by `hydrabench predict`, cached),
  each branch's detections in the right camera matched to the scored ground truth (the run's
  protocol) -> one `fusion.pem.BranchPEM` per branch and each branch's loading on the normal an
  object shares across branches (`fit_shared_loadings`), written as JSON with what it was fitted on.
- `predict`: per frame of a dataset, each branch's detections drawn from its PEM (seed and strength
  given) -> a predictions directory. What a PEM cannot give is absent: no stem features (the deep and
  attention gates read them) and no Faster R-CNN losses (the optimal gate reads them); the gate stored
  is the knowledge gate, which reads only the frame's context label. Its detections are drawn in the
  right camera, so every branch's frame in the manifest is camera_right (the knowledge gate still
  ranks the branches by the model's own frames). Fit on one dataset, check on another: never choose
  anything on a test set.
- `check`: the PEM against the network on held-out frames: per branch and late fusion, mAP per
  context with the network's 95 % sequence-bootstrap interval, and whether the PEM's mAP lies in it;
  recall against range and score calibration, PEM beside network (`plot_check`).

The sweep over strength is `study.experiments.pem_sweep`, the known-answer world `study.experiments.known_answer`.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from sim.errors import UserError

FORMAT = "hydrabench-pem"
VERSION = 1
RECALL_EDGES = (0.0, 10.0, 20.0, 30.0, 40.0, 60.0, 100.0)
SCORE_EDGES = tuple(np.linspace(0.0, 1.0, 11))


def truth_and_features(reader, meta, protocol) -> dict:
    """The scored right-camera ground truth of a frame (as `study.engine.scoring.ground_truth` reads it), with
    ids and truncation, and the per-object features (`fusion.pem.object_table`)."""
    from fusion.pem import object_table
    from fusion.protocol import frame_labels

    labels = reader.labels(int(meta["dataset_index"]))
    truth = frame_labels(labels, meta, protocol)["camera_right"]
    table = object_table(labels["objects"], truth, labels["camera_right"], meta.get("weather") or {})
    return {"ids": list(truth["ids"]), "boxes": np.asarray(truth["boxes"], float).reshape(-1, 4),
            "labels": np.asarray(truth["labels"], int), "difficult": np.asarray(truth["difficult"], bool),
            "distance_m": np.asarray(truth["distance_m"], float)}, table


def image_size(meta) -> tuple[int, int]:
    from sensors.rig import Calibration

    cam = Calibration.from_dict(meta["calibration"]).camera("camera_right")
    return int(cam.width), int(cam.height)


def reference_detections(pred) -> list:
    """[(meta, {branch: Detections in the right camera})] of stored predictions."""
    from fusion.late import to_reference
    from sensors.rig import Calibration

    frames = pred.branch_frames
    out = []
    for meta, per in pred.per_frame:
        calib = Calibration.from_dict(meta["calibration"])
        out.append((meta, {b: to_reference(d, frames[b], calib) for b, d in per.items()}))
    return out


def fit(run_dir, data, out, *, predictions=None, batch_size: int = 4, setup=None, progress: bool = True) -> dict:
    """Fit one PEM per branch of `run_dir` on its predictions on `data` (every frame of a dataset the
    run was not trained on; its own test split otherwise) and write them to `out` (JSON).
    `predictions`: stored predictions of the run on `data` to fit on (else made, or read from the
    run's cache, by `study.engine.predictions.predict`)."""
    from fusion.pem import FitFrame, fit_branch
    from sensors.dataset import DatasetReader
    from study.engine.gate_data import cached_sha256, checkpoint_path, dataset_sha256
    from study.engine.predictions import predict

    t0 = time.perf_counter()
    run_dir, data = Path(run_dir), Path(data)
    if predictions is not None:
        from study.engine.predictions import load
        from study.experiments.compare import check_predictions

        pred = load(predictions)
        check_predictions(pred, run_dir, data)
    else:
        pred = predict(run_dir, data, batch_size=batch_size, setup=setup, progress=progress)
    protocol = pred.manifest["identity"]["protocol"]
    reader = DatasetReader(data)
    per_branch = {b: [] for b in pred.branches}
    for meta, per in reference_detections(pred):
        truth, table = truth_and_features(reader, meta, protocol)
        size = image_size(meta)
        for b, d in per.items():
            per_branch[b].append(FitFrame(d.boxes, d.scores, d.labels, truth, table, meta["context"], size))
    sensors = pred.branch_sensors
    fitted = {b: fit_branch(frames, sensors[b]) for b, frames in per_branch.items()}
    models = {b: m.to_dict() for b, m in fitted.items()}
    loadings = fit_shared_loadings(per_branch, fitted)
    cfg = json.loads((run_dir / "config.json").read_text())
    doc = {"format": FORMAT, "version": VERSION, "run": str(run_dir),
           "checkpoint_sha256": cached_sha256(checkpoint_path(run_dir)), "fit_data": str(data),
           "fit_dataset_sha256": dataset_sha256(data), "fit_frames": len(pred.per_frame),
           "fit_indices": [int(m["dataset_index"]) for m, _ in pred.per_frame], "protocol": protocol,
           "branches": pred.branches, "branch_sensors": {b: list(s) for b, s in sensors.items()},
           "model_frames": {s["name"]: s["frame"] for s in cfg.get("branch_specs", [])} or pred.branch_frames,
           "predictions": str(pred.root), "loadings": loadings, "branch_pem": models}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))
    return {"pem": str(out), "run": str(run_dir), "fit_data": str(data), "frames": len(pred.per_frame),
            "branches": {b: m["counts"] for b, m in models.items()}, "loadings": loadings, "seconds": round(time.perf_counter() - t0, 1)}


def fit_shared_loadings(per_branch: dict, fitted: dict) -> dict:
    """Each branch's loading on the normal its objects share with the other branches
    (`fusion.pem.fit_loadings`), from which true boxes of the fitting frames each branch found
    (`fusion.pem.match`, as the fit matches) and the fitted detection probabilities."""
    from fusion.pem import fit_loadings, match

    branches = list(per_branch)
    found, prob = [], []
    for frames in zip(*(per_branch[b] for b in branches)):
        truth, table = frames[0].truth, frames[0].table
        n = len(truth["boxes"])
        if not n:
            continue
        f = np.zeros((n, len(branches)), bool)
        for k, fr in enumerate(frames):
            m = match(fr.det_boxes, fr.det_scores, truth["boxes"])
            f[m[m >= 0], k] = True
        found.append(f)
        prob.append(np.column_stack([fitted[b].detection_probability(table) for b in branches]))
    if not found:
        return {b: 0.0 for b in branches}
    return dict(zip(branches, fit_loadings(np.vstack(found), np.vstack(prob))))


def load_pem(path) -> dict:
    """A PEM file written by `fit` (UserError naming what is wrong)."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable PEM file ({exc}; see hydrabench pem fit)") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("version") != VERSION:
        raise UserError(f"{path}: not a {FORMAT} v{VERSION} file (see hydrabench pem fit)")
    return doc


def _knowledge(meta, branches, sensors, frames) -> list[float]:
    """The knowledge gate's predicted loss of each branch (`fusion.nets.branch_gates.KnowledgeGate`)."""
    from fusion.nets.branch_gates import branch_quality, sensor_reliability

    rel = sensor_reliability(meta, "meta")
    return [1.0 - branch_quality(rel, sensors[b], frames[b]) for b in branches]


def _appender(arrays: dict):
    def take(name, value):
        arrays.setdefault(name, []).append(value)

    return take


def predict_pem(pem_path, data, out, *, strength: float = 1.0, seed: int = 0, split: str = "auto",
                world: dict | None = None, indices=None, on_fitting_frames: bool = False) -> dict:
    """Draw every branch's detections from the PEM `pem_path` on `data`'s frames (`split` as the run's
    `frames_for` gives them; `indices`: these frames instead) and write them as predictions at `out`
    (`study.engine.predictions` format). `world`: {branch: {context: factor}}, each branch's strength in a
    frame's context multiplied by its factor (`fusion.pem.known_answer_world`); a context it does not
    name keeps `strength`. A frame the PEM was fitted on is refused, unless `on_fitting_frames` (what a
    choice made on the fitting frames draws, when there are no others to choose on: never a test frame)."""
    from fusion.pem import BranchPEM, frame_rng, shared_normals
    from sensors.dataset import DatasetReader
    from study.engine.gate_data import dataset_sha256
    from study.engine.predictions import ARRAYS, write
    from study.engine.predictions import FORMAT as PRED_FORMAT
    from study.engine.predictions import VERSION as PRED_VERSION
    from study.engine.scoring import frames_for

    if not strength > 0:
        raise UserError(f"--strength must be > 0, got {strength}")
    t0 = time.perf_counter()
    doc = load_pem(pem_path)
    data, out = Path(data), Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        have = out / "manifest.json"
        if not (have.is_file() and json.loads(have.read_text()).get("format") == PRED_FORMAT):
            raise UserError(f"--out {out}: exists and is not a predictions directory (choose a new or empty one)")
    run_dir = Path(doc["run"])
    cfg = json.loads((run_dir / "config.json").read_text()) if (run_dir / "config.json").is_file() else {}
    if indices is not None:
        indices, used_split = sorted({int(i) for i in indices}), "indices"
    else:
        indices, used_split = frames_for(cfg, data, split) if cfg else (list(range(len(DatasetReader(data)))), "all")
    if doc["fit_dataset_sha256"] == (sha := dataset_sha256(data)) and not on_fitting_frames:
        fitted = doc.get("fit_indices")
        if fitted is None or set(fitted) & set(indices):
            raise UserError(f"{data}: the PEM was fitted on this dataset; draw it on another (held-out) one"
                            + ("" if fitted is None else " or on frames it was not fitted on"))
    reader = DatasetReader(data)
    branches = list(doc["branches"])
    sensors = {b: tuple(s) for b, s in doc["branch_sensors"].items()}
    pems = {b: BranchPEM.from_dict(doc["branch_pem"][b]) for b in branches}
    loadings = {b: float(v) for b, v in (doc.get("loadings") or {}).items()}
    pem_sha = hashlib.sha256(Path(pem_path).read_bytes()).hexdigest()

    def chunks():
        from study.engine.predictions import CHUNK_FRAMES

        for start in range(0, len(indices), CHUNK_FRAMES):
            part = indices[start:start + CHUNK_FRAMES]
            arrays: dict = {}
            take = _appender(arrays)
            for i in part:
                meta = dict(reader.meta(i), dataset_index=int(i))
                truth, table = truth_and_features(reader, meta, doc["protocol"])
                size = image_size(meta)
                take("indices", np.array([i], np.int64))
                take("meta", np.array([json.dumps(meta)]))
                take("gate.knowledge", np.array([_knowledge(meta, branches, sensors, doc["model_frames"])], np.float32))
                shared = shared_normals(seed, i, len(truth["boxes"]))
                for k, b in enumerate(branches):
                    s_b = strength * (world or {}).get(b, {}).get(meta["context"], 1.0)
                    boxes, scores, labels = pems[b].sample(frame_rng(seed, i, k), truth, table, meta["context"], size,
                                                           s_b, shared, loadings.get(b, 0.0))
                    for prefix in ("det", "ref"):
                        take(f"{prefix}.{b}.count", np.array([len(scores)], np.int32))
                        take(f"{prefix}.{b}.boxes", boxes.astype(np.float32).reshape(-1, 4))
                        take(f"{prefix}.{b}.scores", scores.astype(np.float32))
                        take(f"{prefix}.{b}.labels", labels.astype(np.int16))
            n = len(part)
            arrays = {k: np.concatenate(v) for k, v in arrays.items()}
            arrays["losses"] = np.full((n, len(branches), 4), np.nan, np.float32)
            arrays["features"] = np.zeros((n, 0), np.float16)
            yield arrays

    identity = {"checkpoint_sha256": doc["checkpoint_sha256"], "dataset_sha256": sha, "protocol": doc["protocol"],
                "split": used_split, "frames": len(indices),
                "indices_sha256": hashlib.sha256(json.dumps([int(i) for i in indices]).encode()).hexdigest(),
                "pem_sha256": pem_sha, "strength": float(strength), "seed": int(seed), "branches": branches,
                "gates": ["knowledge"], **({"world": world} if world else {})}
    manifest = {"format": PRED_FORMAT, "version": PRED_VERSION, "identity": identity, "run": str(run_dir),
                "data": str(data), "branches": branches, "branch_frames": {b: "camera_right" for b in branches},
                "branch_sensors": {b: list(s) for b, s in sensors.items()}, "gates": ["knowledge"], "best_gate": None,
                "pem": {"file": str(pem_path), "sha256": pem_sha, "strength": float(strength), "seed": int(seed),
                        "note": "drawn by a perception error model: no stem features or losses (knowledge gate only); "
                                "every branch's boxes are in the right camera"},
                "arrays": {**ARRAYS, "features": "(n, 0): a PEM has no stem features",
                           "losses": "(n, branches, 4) NaN: a PEM has no losses"}}
    manifest["key"] = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]
    write(out, manifest, chunks())
    return {"predictions": str(out), "frames": len(indices), "split": used_split, "strength": float(strength),
            "seed": int(seed), "branches": branches, "seconds": round(time.perf_counter() - t0, 2)}


# ----- the check on held-out frames ------------------------------------------------------------


def curves(per_frame_ref: list, reader, protocol, branches) -> dict:
    """Per branch: recall of the non-difficult true boxes per range bin (`RECALL_EDGES`) and, per score
    bin (`SCORE_EDGES`), the share of detections that are true positives (IoU >= 0.5, same class:
    `fusion.pem.match` then the class compared), with the counts."""
    from fusion.pem import match

    out = {}
    for b in branches:
        found = np.zeros(len(RECALL_EDGES) - 1)
        total = np.zeros(len(RECALL_EDGES) - 1)
        tp = np.zeros(len(SCORE_EDGES) - 1)
        n = np.zeros(len(SCORE_EDGES) - 1)
        for meta, per in per_frame_ref:
            truth, _ = truth_and_features(reader, meta, protocol)
            d = per[b]
            m = match(d.boxes, d.scores, truth["boxes"])
            ok = np.zeros(len(m), bool)
            if len(truth["labels"]):
                ok = (m >= 0) & (np.asarray(d.labels) == truth["labels"][np.maximum(m, 0)])
            hit = np.zeros(len(truth["boxes"]), bool)
            hit[m[ok]] = True
            keep = ~truth["difficult"]
            rb = np.searchsorted(RECALL_EDGES, truth["distance_m"], side="right") - 1
            for j in np.where(keep & (rb >= 0) & (rb < len(total)))[0]:
                total[rb[j]] += 1
                found[rb[j]] += hit[j]
            sb = np.clip(np.searchsorted(SCORE_EDGES, d.scores, side="right") - 1, 0, len(n) - 1)
            np.add.at(n, sb, 1)
            np.add.at(tp, sb, ok.astype(float))
        out[b] = {"recall": [None if t == 0 else round(f / t, 4) for f, t in zip(found, total)],
                  "recall_n": total.astype(int).tolist(),
                  "precision": [None if k == 0 else round(t / k, 4) for t, k in zip(tp, n)],
                  "precision_n": n.astype(int).tolist()}
    return out


def found_matrix(per_frame_ref: list, reader, protocol, branches) -> np.ndarray:
    """(objects, branches) bool: each non-difficult true box found by each branch (IoU >= 0.5, same
    class), over the frames of `per_frame_ref`."""
    from fusion.pem import match

    rows = []
    for meta, per in per_frame_ref:
        truth, _ = truth_and_features(reader, meta, protocol)
        cols = []
        for b in branches:
            d = per[b]
            m = match(d.boxes, d.scores, truth["boxes"])
            hit = np.zeros(len(truth["boxes"]), bool)
            if len(truth["labels"]):
                ok = (m >= 0) & (np.asarray(d.labels) == truth["labels"][np.maximum(m, 0)])
                hit[m[ok]] = True
            cols.append(hit)
        rows.append(np.column_stack(cols)[~truth["difficult"]] if cols else np.zeros((0, 0), bool))
    return np.vstack(rows) if rows else np.zeros((0, len(branches)), bool)


def co_detection(per_frame_ref: list, reader, protocol, branches) -> dict:
    """Do branches find the same objects? Per pair of branches "a|b": P(a finds), P(b finds), P(both)
    and the lift P(both) / (P(a) P(b)) (1: independent; above 1: they find and miss the same objects)."""
    f = found_matrix(per_frame_ref, reader, protocol, branches)
    out = {}
    for i, a in enumerate(branches):
        for j in range(i + 1, len(branches)):
            pa, pb, both = f[:, i].mean(), f[:, j].mean(), (f[:, i] & f[:, j]).mean()
            out[f"{a}|{branches[j]}"] = {"p_a": round(float(pa), 4), "p_b": round(float(pb), 4),
                                         "p_both": round(float(both), 4),
                                         "lift": round(float(both / (pa * pb)), 3) if pa * pb > 0 else None,
                                         "objects": int(len(f))}
    return out


def check(run_dir, test_data, net_pred, pem_preds: dict, *, resamples: int = 500, fusion: str = "soft-nms") -> dict:
    """The PEM predictions `pem_preds` ({label: predictions directory}) against the network's `net_pred`
    on `test_data`: per branch, late fusion and all branches fused, mAP overall and per context, the
    network's 95 % interval (sequence bootstrap) and whether each PEM's mAP is inside it; `curves`
    and `co_detection` of each."""
    from sensors.dataset import DatasetReader
    from study.engine.predictions import load
    from study.engine.scoring import context_bootstrap, fuse_selection, fusion_method, load_run, score
    from study.experiments.compare import check_predictions

    load_run(run_dir)  # the model first: a damaged checkpoint is named before any predictions are read
    reader = DatasetReader(test_data)
    method = fusion_method(fusion)
    net = load(net_pred)
    check_predictions(net, run_dir, test_data)
    protocol = net.manifest["identity"]["protocol"]
    sets = {"network": net}
    for label, p in pem_preds.items():
        sets[label] = load(p)
        check_predictions(sets[label], run_dir, test_data)
    singles = [b for b in net.branches if len(net.branch_sensors[b]) == 1]
    methods = {**{b: (b,) for b in net.branches}, "late": tuple(singles)}
    if len(singles) < len(net.branches):
        methods["all_branches"] = tuple(net.branches)
    result = {"data": str(test_data), "frames": len(net.per_frame), "fusion": fusion, "protocol": protocol,
              "metric": "VOC all-point AP at IoU 0.5, every class, right camera", "resamples": resamples, "sets": {}}
    for label, p in sets.items():
        sources = {name: fuse_selection(p.per_frame, [sel] * len(p.per_frame), p.branch_frames, method)
                   for name, sel in methods.items()}
        scores = {n: score(s, reader, "camera_right", protocol=protocol) for n, s in sources.items()}
        by_sev = by_severity(sources)
        sev_scores = {n: score(s, reader, "camera_right", protocol=protocol)["map_per_context"] for n, s in by_sev.items()}
        entry = {"methods": {n: {"map": s["map"], "map_per_context": s["map_per_context"],
                                 "map_per_severity": sev_scores[n]} for n, s in scores.items()},
                 "curves": curves(reference_detections(p), reader, protocol, p.branches),
                 "co_detection": co_detection(reference_detections(p), reader, protocol, p.branches)}
        if label == "network" and resamples:
            boot = context_bootstrap(sources, reader, "camera_right", protocol=protocol, resamples=resamples,
                                     classes="all", desc="bootstrap the network")
            boot_sev = context_bootstrap(by_sev, reader, "camera_right", protocol=protocol, resamples=resamples,
                                         classes="all", desc="bootstrap the network per severity")
            for n in methods:
                entry["methods"][n]["ci95"] = boot["per_context"]["all"]["map"][n]
                entry["methods"][n]["ci95_per_context"] = {c: g["map"][n] for c, g in boot["per_context"].items()
                                                          if c != "all"}
                entry["methods"][n]["ci95_per_severity"] = {c: g["map"][n] for c, g in boot_sev["per_context"].items()
                                                           if c != "all"}
        result["sets"][label] = entry
    net_m = result["sets"]["network"]["methods"]
    labels = list(pem_preds)
    if len(labels) > 1:
        result["sets"]["pem_mean"] = {"methods": _mean_methods([result["sets"][x]["methods"] for x in labels]),
                                      "of": list(labels)}
        labels.append("pem_mean")
    for label in labels:
        rows = result["sets"][label]["methods"]
        for n, row in rows.items():
            iv = net_m[n].get("ci95")
            row["in_network_ci95"] = None if iv is None or row["map"] is None else bool(iv[0] <= row["map"] <= iv[1])
        for group in ("context", "severity"):
            inside, total = 0, 0
            for n, row in rows.items():
                row[f"in_network_ci95_per_{group}"] = {}
                for c, v in (row.get(f"map_per_{group}") or {}).items():
                    ivc = (net_m[n].get(f"ci95_per_{group}") or {}).get(c)
                    ok = None if ivc is None or v is None else bool(ivc[0] <= v <= ivc[1])
                    row[f"in_network_ci95_per_{group}"][c] = ok
                    if ok is not None:
                        inside, total = inside + ok, total + 1
            result["sets"][label][f"per_{group}_inside"] = {"inside": inside, "of": total}
    return result


def by_severity(sources: dict) -> dict:
    """`sources` with each frame's group the weather severity it was drawn at ("severity 0" is clear
    weather), every condition pooled: the groups `score` and `context_bootstrap` then report per
    context are per severity (ground truth reads no context)."""
    return {n: [({**m, "context": f"severity {m.get('severity', 0)}"}, d) for m, d in s] for n, s in sources.items()}


def _mean_methods(sets: list) -> dict:
    """Per method the mean mAP over PEM draws (overall, per context and per severity), with the smallest
    and largest."""
    out = {}
    for n in sets[0]:
        maps = [m[n]["map"] for m in sets if m[n]["map"] is not None]
        out[n] = {"map": round(float(np.mean(maps)), 4) if maps else None,
                  "map_range": [min(maps), max(maps)] if maps else None}
        for group in ("map_per_context", "map_per_severity"):
            per = {c: [m[n][group].get(c) for m in sets] for c in sets[0][n].get(group, {})}
            out[n][group] = {c: round(float(np.mean([v for v in vs if v is not None])), 4)
                             if any(v is not None for v in vs) else None for c, vs in per.items()}
    return out


def plot_check(result: dict, path, label: str = "pem") -> None:
    """Recall against range and score calibration per branch, the PEM `label` beside the network."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    net = result["sets"]["network"]["curves"]
    pem = result["sets"][label]["curves"]  # one draw
    branches = list(net)
    fig, axes = plt.subplots(2, len(branches), figsize=(3.4 * len(branches), 6.4), squeeze=False)
    rc = [(a + b) / 2 for a, b in zip(RECALL_EDGES[:-1], RECALL_EDGES[1:])]
    sc = [(a + b) / 2 for a, b in zip(SCORE_EDGES[:-1], SCORE_EDGES[1:])]
    for j, b in enumerate(branches):
        ax = axes[0, j]
        for name, cur, style in (("network", net[b], "o-"), ("PEM", pem[b], "s--")):
            ax.plot(rc, [np.nan if v is None else v for v in cur["recall"]], style, label=name)
        ax.set_title(b)
        ax.set_xlabel("range [m]")
        ax.set_ylim(0, 1)
        if j == 0:
            ax.set_ylabel("recall (IoU 0.5, class)")
            ax.legend(fontsize=8)
        ax = axes[1, j]
        ax.plot([0, 1], [0, 1], ":", color="grey", lw=0.8)
        for name, cur, style in (("network", net[b], "o-"), ("PEM", pem[b], "s--")):
            ax.plot(sc, [np.nan if v is None else v for v in cur["precision"]], style, label=name)
        ax.set_xlabel("score")
        ax.set_ylim(0, 1)
        if j == 0:
            ax.set_ylabel("share true positive")
    fig.suptitle(f"PEM ({label}) vs network on {Path(result['data']).name}: recall by range, score calibration")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_check(r: dict) -> str:
    """The check as text: per method the network's mAP with its interval and each PEM's mAP."""
    net = r["sets"]["network"]["methods"]
    pems = [k for k in r["sets"] if k != "network"]
    lines = [f"{r['frames']} frames of {r['data']}; {r['metric']}",
             f"{'method':14s} {'network [95 % interval]':28s} " + " ".join(f"{p:>14s}" for p in pems)]
    for n, row in net.items():
        iv = row.get("ci95")
        cell = f"{row['map']:.3f}" + (f" [{iv[0]:.3f}, {iv[1]:.3f}]" if iv else "") if row["map"] is not None else "-"
        pc = []
        for p in pems:
            m = r["sets"][p]["methods"][n]
            mark = {True: " in", False: " out", None: ""}[m.get("in_network_ci95")]
            pc.append(f"{'-' if m['map'] is None else format(m['map'], '.3f')}{mark:>4s}".rjust(14))
        lines.append(f"{n:14s} {cell:28s} " + " ".join(pc))
    for p in pems:
        c = r["sets"][p]["per_context_inside"]
        lines.append(f"{p}: per-context mAP inside the network's interval in {c['inside']} of {c['of']} (method, context)")
        c = r["sets"][p]["per_severity_inside"]
        lines.append(f"{p}: per-severity mAP inside the network's interval in {c['inside']} of {c['of']} "
                     "(method, severity; every condition pooled)")
    return "\n".join(lines)

