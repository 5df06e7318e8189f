"""`hydrabench evaluate`: VOC mAP@0.5 of a trained run's branches, fused in the right camera.

Each selected branch runs on the frames; its detections are mapped to the right camera with the
frame's calibration (BEV branches through HydraFusion's Appendix A, left-camera branches through
the stereo disparity) and fused with NMS, Soft-NMS or WBF (HydraFusion 4.4 / 5.2.1 thresholds:
IoU 0.4, skip 0.01, sigma 0.5). Ground truth follows the evaluation protocol (--protocol, default:
the one the run trained on): `reference` = the projected 3D box of every actor within range that
some sensor observes in the clean render (world truth), `visible` = the right camera's visible-pixel
boxes (under 8 px tall at 188 rows, > 80 % occluded or > 60 % truncated: difficult), `bev` = the BEV
branches on their own grid only. Difficult boxes are ignored, as VOC does. mAP is the mean of
all-point interpolated AP over the classes that have ground truth; the vehicle mAP is also given per
range bin (0-15, 15-30, 30-50, 50-100 m from the radar).

Gates (HydraFusion 4.2, Tables 6 and 7): --gate NAME --k K wires that gate into the network, so
per frame only the K branches it selects run, and fuses them; --all-gates reports mAP for every
gate x fusion method x k in 1, 3, 5, all (`map_table`: gate -> fusion -> k -> mAP) and how often
each gate selects each branch (`selection_rate`: gate -> k -> branch -> percent). The deep and
attention gates must be trained first (hydrabench train-gate); the optimal gate reads each frame's
a-posteriori branch losses from the run's gate dataset (built when missing).
"""

from __future__ import annotations

from fusion.metrics import MAX_BOOTSTRAP
from sensors.dataset import DatasetReader
from sim.errors import UserError
from sim.weather import WeatherState
from study.engine.device import resolve_device


def evaluate(run_dir, data, branches="all", fusion="soft-nms", split="auto", weights=None, checkpoint="latest",
             batch_size: int = 4, contexts=(), twins: bool = False, protocol: str | None = None,
             setup=None, bootstrap: int = 0) -> dict:
    """mAP of `branches` of a run fused with `fusion` (see the module doc). `twins`: also run them on
    the clear-weather twins of the same frames and report what each branch keeps ("twins").
    `protocol`: reference | visible | bev (None: the run's own). `setup`: a `study.engine.device.DeviceSetup`
    (default: --device auto, threads = the cores available). `bootstrap`: 95 % intervals from that
    many sequence resamples: with `twins` of each degraded / clear / retained figure, without of
    each branch's and the fused vehicle mAP per context and of their differences ("ci95")."""

    from fusion.protocol import PROTOCOLS, Protocol
    from study.engine.scoring import (
        bev_crop_of,
        frames_for,
        fused,
        fusion_method,
        load_run,
        native,
        run_branches,
        score,
    )
    from study.engine.train import run_protocol

    setup = setup or resolve_device(purpose="eval")
    method = fusion_method(fusion)
    if not 0 <= bootstrap <= MAX_BOOTSTRAP:
        raise UserError(f"--bootstrap must be 0..{MAX_BOOTSTRAP} draws, got {bootstrap}")
    if protocol is not None and protocol not in PROTOCOLS:
        raise UserError(f"--protocol: unknown protocol {protocol!r} (choose from: {', '.join(PROTOCOLS)})")
    model, cfg = load_run(run_dir, checkpoint, device=setup.device)
    proto = Protocol(protocol or run_protocol(cfg))
    names = list(model.branches) if branches in ("all", None, "") else [b.strip() for b in branches.split(",") if b.strip()]
    bad = [b for b in names if b not in model.branches]
    if bad:
        raise UserError(f"unknown branch {bad[0]!r} (this run has: {', '.join(model.branches)})")
    if proto.name == "bev":
        if branches in ("all", None, ""):
            names = [b for b in names if model.branch_frames[b] == "bev"]
        cam = [b for b in names if model.branch_frames[b] != "bev"]
        if cam or not names:
            raise UserError(f"--protocol bev scores BEV branches on their own grid; {cam[0] if cam else 'this run'!r} "
                            "has none" if not cam else f"--protocol bev scores BEV branches on their own grid; "
                            f"{cam[0]!r} is a camera-view branch (use --protocol reference)")
    weights = weights or {}
    bad = [b for b in weights if b not in names]
    if bad:
        raise UserError(f"--weights names {bad[0]!r}, which is not an evaluated branch")
    indices, used_split = frames_for(cfg, data, split)
    if not indices:
        raise UserError(f"no frames to evaluate in the {used_split!r} split of {data}")
    reader = DatasetReader(data)
    if contexts:
        present = sorted({reader.meta(i)["context"] for i in indices})
        bad = [c for c in contexts if c not in present]
        if bad:
            raise UserError(f"--contexts: {bad[0]!r} is not in the {used_split} split (it has: {', '.join(present)})")
        indices = [i for i in indices if reader.meta(i)["context"] in contexts]
    if bootstrap and not twins and proto.name == "bev":
        raise UserError("--bootstrap without --twins gives intervals per context in the right camera; "
                        "--protocol bev has no right-camera result (add --twins, or use --protocol reference)")
    if twins and not reader.manifest["config"].get("twins"):
        raise UserError(f"--twins: {data} has no clear-weather twins (generate it with --twins)")
    opts = {"workers": setup.workers, "amp": setup.amp}
    per_frame = run_branches(model, data, indices, names, batch_size=batch_size, **opts)
    frames = model.branch_frames
    crop = bev_crop_of(model, reader)
    native_scores = {b: score(native(per_frame, b), reader, frames[b], crop, proto) for b in names}
    if proto.name == "bev":
        # RADIATE's native radar metric: each BEV branch on its own grid; no camera-frame fusion
        result = {"protocol": proto.describe(), "per_branch": native_scores}
    else:
        fused_frames = fused(per_frame, names, frames, method, weights)
        alone_frames = {b: fused(per_frame, [b], frames, method) for b in names}
        result = score(fused_frames, reader, "camera_right", protocol=proto)
        alone = {b: score(alone_frames[b], reader, "camera_right", protocol=proto) for b in names}
        result["map_per_branch_reference"] = {b: alone[b]["map"] for b in names}
        # each branch alone in the fused reference frame, broken down as the fused result is (Table 1)
        keys = ("map_vehicles", "map_vehicles_per_context", "map_vehicles_per_severity", "map_vehicles_per_range",
                "map_vehicles_per_context_range")
        result["per_branch_reference"] = {b: {k: alone[b][k] for k in keys} for b in names}
        if bootstrap and not twins:
            from study.engine.scoring import context_bootstrap

            result["ci95"] = context_bootstrap({"fused": fused_frames, **alone_frames}, reader, "camera_right", proto,
                                               bootstrap)
    if twins:
        result["twins"] = _twins(model, data, indices, names, frames, method, weights, batch_size, per_frame, reader,
                                 proto, opts, bootstrap)
    result.update({
        "branches": names, "fusion": method, "split": used_split, "contexts": sorted(set(contexts)) or "all",
        "run": str(run_dir), "data": str(data), "frames": len(per_frame),
        "map_per_branch_native": {b: native_scores[b]["map"] for b in names},
        "map_vehicles_per_branch_native": {b: native_scores[b]["map_vehicles"] for b in names},
        "metric": "VOC all-point AP at IoU 0.5, difficult ground truth ignored, mean over classes with ground truth",
        "device": setup.describe(),
    })
    return result


def _twins(model, data, indices, names, frames, method, weights, batch_size, per_frame, reader, protocol=None,
           run=None, bootstrap: int = 0) -> dict:
    """The same frames in clear weather: per branch (in its own frame, vehicle classes) the mAP on
    the degraded frames, on their clear twins, and their ratio, overall and per severity; and the same
    for the fused result. The frames and labels are identical; only the weather differs."""
    from sensors.dataset import DatasetReader
    from study.engine.scoring import (
        bev_crop_of,
        fused,
        native,
        operating_point,
        paired_bootstrap,
        recall_by_visibility,
        run_branches,
        score,
    )

    clear_reader = DatasetReader(data, clear=True)
    clear_frames = run_branches(model, data, indices, names, batch_size=batch_size, progress="clear twins",
                                clear=True, **(run or {}))
    crop = bev_crop_of(model, reader)
    mor = {meta["dataset_index"]: meta["weather"]["visibility_m"] for meta, _ in per_frame}

    def by_visibility(deg_frames, clr_frames, frame, bev) -> dict:
        deg = recall_by_visibility(deg_frames, reader, frame, bev, visibility=mor, protocol=protocol)
        clr = recall_by_visibility(clr_frames, clear_reader, frame, bev, visibility=mor, protocol=protocol)
        return {k: {"objects": v["objects"], "degraded": v["recall"], "clear": clr[k]["recall"],
                    "contrast": v["contrast"]} for k, v in deg.items()}

    def pair(deg_frames, clr_frames, frame, bev, name) -> dict:
        deg = score(deg_frames, reader, frame, bev, protocol)
        clr = score(clr_frames, clear_reader, frame, bev, protocol)
        op_d = operating_point(deg_frames, reader, frame, bev, protocol=protocol)
        op_c = operating_point(clr_frames, clear_reader, frame, bev, protocol=protocol)
        sev = sorted(set(deg["map_vehicles_per_severity"]) | set(clr["map_vehicles_per_severity"]), key=int)
        rng = {k: {"degraded": v, "clear": clr["map_vehicles_per_range"].get(k),
                   "retained": _ratio(v, clr["map_vehicles_per_range"].get(k))}
               for k, v in deg["map_vehicles_per_range"].items()}
        out_pair = {
            "degraded": deg["map_vehicles"], "clear": clr["map_vehicles"],
            "retained": _ratio(deg["map_vehicles"], clr["map_vehicles"]),
            "per_range": rng,
            "at_score_0.5": {"degraded": {k: op_d[k] for k in ("recall", "precision")},
                             "clear": {k: op_c[k] for k in ("recall", "precision")},
                             "by_distance_over_visibility": by_visibility(deg_frames, clr_frames, frame, bev)},
            "per_severity": {s: {"degraded": deg["map_vehicles_per_severity"].get(s),
                                 "clear": clr["map_vehicles_per_severity"].get(s),
                                 "retained": _ratio(deg["map_vehicles_per_severity"].get(s),
                                                    clr["map_vehicles_per_severity"].get(s)),
                                 "at_score_0.5": {"degraded": op_d["per_severity"].get(s),
                                                  "clear": op_c["per_severity"].get(s)}} for s in sev}}
        if bootstrap:
            out_pair["ci95"] = paired_bootstrap(deg_frames, clr_frames, reader, clear_reader, frame, bev, protocol,
                                                bootstrap, severities=sev, desc=f"bootstrap {name}")
        return out_pair

    stale = stale_twins(reader, clear_reader, indices)
    out = {"metric": "vehicle-class mAP@0.5 (car, van, truck, bus), each branch in its own frame; retained = "
                     "degraded / clear; at_score_0.5: recall and precision of the detections scoring >= 0.5, and the "
                     "recall binned by object distance / the degraded frame's visibility (MOR), with the "
                     "Koschmieder contrast exp(-ln(20) d / MOR) left at the bin edges",
           "branches": {}}
    if stale:
        out["warning"] = (f"{stale} of {len(indices)} twins were made by sensor model version 2 or older: a twin of a "
                          "fog, rain or snow frame was rendered with direct sun instead of the frame's overcast sky, so "
                          "its camera differs by the light as well as by the condition; regenerate the dataset")
    for b in names:
        out["branches"][b] = pair(native(per_frame, b), native(clear_frames, b), frames[b], crop, b)
    if protocol is None or protocol.name != "bev":
        out["fused"] = pair(fused(per_frame, names, frames, method, weights),
                            fused(clear_frames, names, frames, method, weights), "camera_right", None, "fused")
    return out


def stale_twins(reader, clear_reader, indices) -> int:
    """How many of these frames have an overcast sky but a twin without the `overcast` record (made
    before sensor model version 3, when twins of fog, rain and snow frames lost the overcast sky)."""
    n = 0
    for i in indices:
        w = reader.meta(i)["weather"]
        # the sky the old rule gave the frame (WeatherState.sky_overcast with overcast=None)
        sky = WeatherState(fog_visibility_m=w["fog_visibility_m"], rain_mm_h=w["rain_mm_h"], snow_mm_h=w["snow_mm_h"])
        n += bool(sky.sky_overcast and "overcast" not in clear_reader.meta(i)["weather"])
    return n


def _ratio(a, b):
    return None if a is None or not b else round(a / b, 3)
