"""A dataset written in nuScenes v1.0 format, which the nuScenes devkit loads (docs/nuscenes.md).

`export_nuscenes(data, out)` writes, from a dataset directory alone (and the road layout its
sequences' seeds rebuild, for the map masks):

    out/v1.0-hydrabench/   the thirteen tables (scene, sample, sample_data, sample_annotation,
                           instance, category, attribute, visibility, sensor, calibrated_sensor,
                           ego_pose, log, map) as JSON lists, and splits.json (the devkit's custom
                           splits: scene names per split)
    out/samples/CAM_FRONT/              the right camera (hydrabench's fused reference), PNG
    out/samples/CAM_FRONT_STEREO_LEFT/  the left camera, PNG
    out/samples/LIDAR_TOP/              the lidar sweep, .pcd.bin: float32 x, y, z, intensity, ring
    out/samples/RADAR_TOP/              the radar's CFAR peaks, .pcd (nuScenes' 18 radar fields)
    out/maps/                           one semantic-prior mask per log (road and sidewalks, 0.1 m)
    out/hydrabench_export.json          what was exported from what: counts, the class table, splits

A hydrabench sequence is a nuScenes scene (with its own log and map); a frame is a sample whose
four sample_data (one per sensor, all key frames) share its timestamp; an actor is an instance
whose token is the same in every frame of its sequence. Boxes, poses and calibrations are read from
each frame (`meta.calibration`, `meta.ego_pose`, `labels.objects`), never from constants. Tokens
are hashes of the dataset's shard checksums and the record's ids, so exporting the same dataset
twice writes the same bytes.

Frames: nuScenes' ego frame is hydrabench's (x forward, y left, z up); its global frame is a log's
map frame: hydrabench's world frame shifted so that the log's map mask starts at (0, 0) (the devkit
reads map masks with the origin at their lower-left corner). Sizes are (width, length, height) and
rotations quaternions (w, x, y, z), as nuScenes writes them.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.errors import UserError

VERSION = "v1.0-hydrabench"
TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
          "scene", "sample", "sample_data", "sample_annotation", "map")

# hydrabench sensor -> (nuScenes channel, modality). The right camera is CAM_FRONT: it is the frame
# every fused detection is scored in (HydraFusion 5.2.3); the left eye is not nuScenes' CAM_FRONT_LEFT
# (a camera turned 55 degrees left), so it gets a name of its own.
CHANNELS = {"camera_right": ("CAM_FRONT", "camera"), "camera_left": ("CAM_FRONT_STEREO_LEFT", "camera"),
            "lidar": ("LIDAR_TOP", "lidar"), "radar": ("RADAR_TOP", "radar")}

# RADIATE class (sim.actors.CLASSES, ids 1..8) -> (nuScenes category, nuScenes detection name).
# nuScenes files vans under vehicle.car ("sedans, hatch-backs, wagons, vans, mini-vans, SUVs") and
# has no category for a group of pedestrians: its annotators box each person, so a group is
# human.pedestrian.adult, one box. The hydrabench class stays on every instance ("hydrabench").
CLASS_TABLE = {
    "car": ("vehicle.car", "car"),
    "van": ("vehicle.car", "car"),
    "truck": ("vehicle.truck", "truck"),
    "bus": ("vehicle.bus.rigid", "bus"),
    "motorbike": ("vehicle.motorcycle", "motorcycle"),
    "bicycle": ("vehicle.bicycle", "bicycle"),
    "pedestrian": ("human.pedestrian.adult", "pedestrian"),
    "group_of_pedestrians": ("human.pedestrian.adult", "pedestrian"),
}
CATEGORY_DESCRIPTIONS = {
    "vehicle.car": "hydrabench car and van",
    "vehicle.truck": "hydrabench truck",
    "vehicle.bus.rigid": "hydrabench bus (single-deck city bus)",
    "vehicle.motorcycle": "hydrabench motorbike, with its rider",
    "vehicle.bicycle": "hydrabench bicycle, with its rider",
    "human.pedestrian.adult": "hydrabench pedestrian, and group of pedestrians (one box per group)",
}
ATTRIBUTES = {
    "vehicle.moving": "Vehicle is moving.",
    "vehicle.stopped": "Vehicle, with a driver/rider in/on it, is currently stationary but has an intent to move.",
    "vehicle.parked": "Vehicle is stationary (usually for longer duration) with no immediate intent to move.",
    "cycle.with_rider": "There is a rider on the bicycle or motorcycle.",
    "cycle.without_rider": "There is NO rider on the bicycle or motorcycle.",
    "pedestrian.sitting_lying_down": "The human is sitting or lying down.",
    "pedestrian.standing": "The human is standing.",
    "pedestrian.moving": "The human is moving.",
}
# nuScenes' visibility levels: the share of the object visible in the cameras, in four bins
VISIBILITY = (("1", "v0-40", 0.4, "visibility of whole object is between 0 and 40%"),
              ("2", "v40-60", 0.6, "visibility of whole object is between 40 and 60%"),
              ("3", "v60-80", 0.8, "visibility of whole object is between 60 and 80%"),
              ("4", "v80-100", 1.0, "visibility of whole object is between 80 and 100%"))
MOVING_M_S = 0.2  # below this speed an actor is stopped / standing

# Radar: cell-averaging CFAR along range on the linear power of the polar image, then a 3x3 peak test
CFAR_TRAIN = 8  # training cells on each side along range
CFAR_GUARD = 2  # guard cells on each side
CFAR_PFA = 1e-4  # false-alarm probability per cell on exponential (speckle + noise) power
RADAR_FIELDS = ("x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state x_rms y_rms "
                "invalid_state pdh0 vx_rms vy_rms").split()
RADAR_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("dyn_prop", "i1"), ("id", "<i2"),
                        ("rcs", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vx_comp", "<f4"), ("vy_comp", "<f4"),
                        ("is_quality_valid", "i1"), ("ambig_state", "i1"), ("x_rms", "i1"), ("y_rms", "i1"),
                        ("invalid_state", "i1"), ("pdh0", "i1"), ("vx_rms", "i1"), ("vy_rms", "i1")])
DYN_PROP_UNKNOWN = 4  # ARS-408 dynProp "unknown": a Navtech measures no Doppler
AMBIG_UNAMBIGUOUS = 3  # no Doppler ambiguity to resolve; also what the devkit's default filter keeps
INVALID_STATE_VALID = 0

MAP_RESOLUTION_M = 0.1  # the devkit reads map masks at 0.1 m per pixel unless told otherwise
MAP_MARGIN_M = 120.0  # around the ego's path: the sensors' range (sensors.frame.SENSOR_RANGE_M) and some
TIME_BASE_US = 1_577_836_800_000_000  # 2020-01-01 00:00 UTC: a sequence k starts k hours later
SCENE_SPACING_US = 3_600_000_000  # sequences last at most an hour (sim.scenario.MAX_DURATION_S)


# ---------------------------------------------------------------------------------------------
# small pure pieces


def make_token(salt: str, *parts) -> str:
    """A 32-hex-digit nuScenes token: sha256 of the dataset's salt and the record's ids."""
    return hashlib.sha256("|".join([salt, *map(str, parts)]).encode()).hexdigest()[:32]


def quaternion_from_matrix(R) -> list[float]:
    """(w, x, y, z) unit quaternion of a 3x3 rotation matrix (Shepperd's method), w >= 0."""
    R = np.asarray(R, float)
    t = np.trace(R)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q) / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return [round(float(v), 9) + 0.0 for v in q]


def yaw_quaternion(yaw: float) -> list[float]:
    """(w, x, y, z) of a rotation by `yaw` [rad] about +z."""
    return [round(math.cos(yaw / 2), 9) + 0.0, 0.0, 0.0, round(math.sin(yaw / 2), 9) + 0.0]


def visibility_level(share: float) -> str:
    """nuScenes visibility token ("1".."4") of the visible share of an object (0..1)."""
    for token, _, upper, _ in VISIBILITY:
        if share <= upper:
            return token
    return VISIBILITY[-1][0]


def attribute_of(cls: str, speed: float) -> str:
    """The nuScenes attribute of an actor of RADIATE class `cls` moving at `speed` [m/s]. hydrabench's
    two-wheelers always carry a rider; a stationary vehicle is "stopped" (the labels do not say which
    cars are parked)."""
    moving = speed >= MOVING_M_S
    if cls in ("motorbike", "bicycle"):
        return "cycle.with_rider"
    if cls in ("pedestrian", "group_of_pedestrians"):
        return "pedestrian.moving" if moving else "pedestrian.standing"
    return "vehicle.moving" if moving else "vehicle.stopped"


def radar_points(polar: np.ndarray, range_resolution_m: float) -> np.ndarray:
    """The CFAR peaks of a Navtech-like polar power image as nuScenes radar points (RADAR_DTYPE).

    `polar`: (A, B) uint8 counts, 0.5 dB each (sensors.radar.to_counts), row a at azimuth 2 pi a / A
    counter-clockwise from the radar's +x, column b at range (b + 0.5) * `range_resolution_m`.
    A cell is a point when its linear power exceeds the cell-averaging CFAR threshold along range
    (CFAR_TRAIN training and CFAR_GUARD guard cells on each side; scale for CFAR_PFA on exponential
    power) and no 3x3 neighbour (azimuth wraps) is stronger. Fields: x, y in the radar frame, z = 0;
    rcs the radar equation's estimate 10 log10((P - N) R^4 / C) [dBsm] with the rig's constant C
    (sensors.radar.RADAR_CONSTANT, unit two-way gain, no weather attenuation); the velocities 0 and
    dyn_prop "unknown" (no Doppler); id the point's index; the ARS-408 state fields set to "valid,
    unambiguous" so the devkit's default filters keep every point."""
    from sensors.radar import RADAR_CONSTANT, counts_to_db

    power = 10.0 ** (counts_to_db(np.asarray(polar)) / 10.0)
    A, B = power.shape
    csum = np.concatenate([np.zeros((A, 1)), np.cumsum(power, axis=1)], axis=1)
    b = np.arange(B)

    def window(lo, hi):  # sum and count of cells [lo, hi) per range column, clipped to the image
        lo, hi = np.clip(lo, 0, B), np.clip(hi, 0, B)
        return csum[:, hi] - csum[:, lo], (hi - lo)

    s1, n1 = window(b - CFAR_GUARD - CFAR_TRAIN, b - CFAR_GUARD)
    s2, n2 = window(b + CFAR_GUARD + 1, b + CFAR_GUARD + CFAR_TRAIN + 1)
    n = np.maximum(n1 + n2, 1)
    noise = (s1 + s2) / n
    alpha = n * (CFAR_PFA ** (-1.0 / n) - 1.0)
    hit = power > alpha * noise
    padded = np.pad(np.concatenate([power[-1:], power, power[:1]], axis=0), ((0, 0), (1, 1)), constant_values=-1.0)
    for da in (-1, 0, 1):
        for db in (-1, 0, 1):
            if da or db:
                hit &= power >= padded[1 + da:1 + da + A, 1 + db:1 + db + B]
    rows, cols = np.nonzero(hit)
    phi = 2.0 * np.pi * rows / A
    r = (cols + 0.5) * range_resolution_m
    signal = np.maximum(power[rows, cols] - noise[rows, cols], 1e-12)
    pts = np.zeros(len(rows), RADAR_DTYPE)
    pts["x"], pts["y"] = r * np.cos(phi), r * np.sin(phi)
    pts["id"] = np.arange(len(rows)) % 32768
    pts["rcs"] = 10.0 * np.log10(signal * r**4 / RADAR_CONSTANT)
    pts["dyn_prop"] = DYN_PROP_UNKNOWN
    pts["is_quality_valid"] = 1
    pts["ambig_state"] = AMBIG_UNAMBIGUOUS
    pts["invalid_state"] = INVALID_STATE_VALID
    pts["pdh0"] = 1  # ARS-408 "false alarm probability < 25 %": what CFAR_PFA promises per cell
    return pts


def radar_pcd_bytes(points: np.ndarray) -> bytes:
    """A nuScenes radar .pcd file (PCD v0.7 ASCII header, binary records) of RADAR_DTYPE points.

    The devkit's reader wants at least one point and one byte past the last record: an empty scan
    is written as one point of NaNs (the devkit's own mark of an empty cloud), and the data end with
    a newline."""
    if len(points) == 0:
        points = np.zeros(1, RADAR_DTYPE)
        for name in ("x", "y", "z", "rcs", "vx", "vy", "vx_comp", "vy_comp"):
            points[name] = np.nan
    sizes = " ".join(str(RADAR_DTYPE[f].itemsize) for f in RADAR_FIELDS)
    types = " ".join("F" if RADAR_DTYPE[f].kind == "f" else "I" for f in RADAR_FIELDS)
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
              f"FIELDS {' '.join(RADAR_FIELDS)}\nSIZE {sizes}\nTYPE {types}\n"
              f"COUNT {' '.join('1' for _ in RADAR_FIELDS)}\nWIDTH {len(points)}\nHEIGHT 1\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA binary\n")
    return header.encode() + np.ascontiguousarray(points, RADAR_DTYPE).tobytes() + b"\n"


def read_radar_pcd(path: str | Path) -> np.ndarray:
    """A radar .pcd written by `radar_pcd_bytes`, back as RADAR_DTYPE points (no devkit needed)."""
    data = Path(path).read_bytes()
    head, _, body = data.partition(b"DATA binary\n")
    width = int(next(ln.split()[1] for ln in head.decode().splitlines() if ln.startswith("WIDTH")))
    pts = np.frombuffer(body[: width * RADAR_DTYPE.itemsize], RADAR_DTYPE)
    return pts[np.isfinite(pts["x"])]


def lidar_bin_bytes(points: np.ndarray) -> bytes:
    """nuScenes .pcd.bin: float32 (x, y, z, intensity, ring) per point. hydrabench's intensity (0..1)
    is scaled to nuScenes' 0..255."""
    out = np.asarray(points, np.float32).copy()
    out[:, 3] *= 255.0
    return out.astype("<f4").tobytes()


def points_in_footprint(xy: np.ndarray, center, size, yaw: float) -> np.ndarray:
    """(N,) bool: points `xy` (ego frame) inside a box's ground footprint (length size[0] along yaw)."""
    d = np.asarray(xy, float) - np.asarray(center, float)[:2]
    c, s = math.cos(yaw), math.sin(yaw)
    along, across = d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c
    return (np.abs(along) <= size[0] / 2) & (np.abs(across) <= size[1] / 2)


def _round(values, nd: int = 6) -> list[float]:
    return [round(float(v), nd) + 0.0 for v in values]  # + 0.0: no "-0.0" in the files


def _dump(obj) -> bytes:
    return json.dumps(obj, indent=0, separators=(",", ":"), allow_nan=False).encode()


# ---------------------------------------------------------------------------------------------
# the road of a sequence, for its map mask


def _frame_config(manifest: dict, frame: int) -> dict:
    """The generation config a frame was made with (a view's part's own config)."""
    for part in (manifest.get("parts") or {}).values():
        if part["start"] <= frame < part["stop"]:
            return part["config"]
    return manifest["config"]


def sequence_road(manifest: dict, shard: dict, first_frame: int, first_meta: dict):
    """The drivable surface and sidewalks (a shapely geometry, world frame) of a shard's sequence,
    rebuilt by simulating its scenario from the seed the manifest records. UserError when the
    simulation does not reproduce the frame's ego pose (a dataset from another hydrabench)."""
    from shapely.ops import unary_union

    from sim.scenario import ScenarioSpec, Simulator

    cfg = _frame_config(manifest, first_frame)
    try:
        spec = ScenarioSpec(context=shard["context"], severity=shard["severity"], seed=shard["seed"],
                            frames=shard["frames"], frame_rate_hz=cfg["frame_rate_hz"], profile=cfg["profile"],
                            transition=shard.get("transition", "none"))
    except KeyError as exc:
        raise UserError(f"{shard['name']}: the manifest does not say its {exc.args[0]}; cannot rebuild its road "
                        "for the map") from None
    scene = next(iter(Simulator(spec).scenes()))
    if not np.allclose(scene.ego.pose, np.asarray(first_meta["ego_pose"], float), atol=1e-3):
        raise UserError(f"{shard['name']}: simulating its seed does not give the ego pose its frames record "
                        "(a dataset made by another version of hydrabench?); cannot rebuild its road for the map")
    return unary_union([scene.road.road, scene.road.sidewalks])


def map_mask(geometry, region: tuple[float, float, float, float]) -> np.ndarray:
    """(H, W) uint8 mask at MAP_RESOLUTION_M of `geometry` (world frame) over `region` (xmin, ymin,
    xmax, ymax): 255 on it, 0 elsewhere; row 0 is the top (ymax), as the devkit reads map masks."""
    from PIL import Image, ImageDraw
    from shapely.geometry import box as shapely_box

    xmin, ymin, xmax, ymax = region
    W = int(math.ceil((xmax - xmin) / MAP_RESOLUTION_M))
    H = int(math.ceil((ymax - ymin) / MAP_RESOLUTION_M))
    img = Image.new("L", (W, H), 0)
    draw = ImageDraw.Draw(img)
    clipped = geometry.intersection(shapely_box(xmin, ymin, xmax, ymax))

    def px(coords):
        c = np.asarray(coords, float)
        return [(float((x - xmin) / MAP_RESOLUTION_M), float(H - (y - ymin) / MAP_RESOLUTION_M)) for x, y in c]

    polys = getattr(clipped, "geoms", [clipped])
    for poly in polys:
        if poly.geom_type != "Polygon" or poly.is_empty:
            continue
        draw.polygon(px(poly.exterior.coords), fill=255)
        for hole in poly.interiors:
            draw.polygon(px(hole.coords), fill=0)
    return np.asarray(img)


def _png_bytes(array: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(array)).save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


# ---------------------------------------------------------------------------------------------
# the export


def dataset_salt(manifest: dict, clear: bool = False) -> str:
    """What makes a dataset's tokens its own: its shards' names and checksums (and whether the
    clear-weather twins are exported)."""
    ident = [[s["name"], s["sha256"]] for s in manifest["shards"]] + [["clear", bool(clear)]]
    return hashlib.sha256(json.dumps(ident).encode()).hexdigest()


def scene_name(shard: str) -> str:
    """nuScenes scene name of a hydrabench shard (shard-00012 -> scene-00012)."""
    return "scene-" + shard.split("-", 1)[1]


def _description(meta: dict) -> str:
    w = meta["weather"]
    cond = "+".join(meta["conditions"]) or "clear"
    lens = w.get("lens_coverage_pct", [0, 0])
    return (f"hydrabench {meta['context']}: layout {meta['layout']}, condition {cond}, severity {meta['severity']}; "
            f"visibility {w['visibility_m']:g} m, rain {w['rain_mm_h']:g} mm/h, snow {w['snow_mm_h']:g} mm/h, "
            f"{w['illuminance_lux']:g} lux, lens coverage {lens[0]:g}/{lens[1]:g} %")


def export_nuscenes(data: str | Path, out: str | Path, *, splits: dict[str, list[str]] | None = None,
                    clear: bool = False, progress: bool = False) -> dict:
    """Write dataset `data` in nuScenes format into `out` (see the module docstring); returns a
    summary (counts of every table, files, bytes).

    `splits`: {split name: [shard names]}, written as `splits.json` with scene names (the devkit's
    custom splits; names must not be nuScenes' own: train, val, test, mini_train, ...).
    `clear`: export the clear-weather twins instead of the frames. `out` must be absent or an empty
    directory; the export is written beside it under a temporary name and renamed when complete, so
    an interrupted export leaves nothing at `out`."""
    from sensors.dataset import DatasetReader
    from sim.actors import CLASSES
    from sim.progress import progress as progress_bar

    reader = DatasetReader(Path(data), clear=clear)
    manifest = reader.manifest
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"{out} is not empty: the nuScenes export needs a new or empty folder")
    salt = dataset_salt(manifest, clear)
    shard_names = [s["name"] for s in manifest["shards"]]
    for name, members in (splits or {}).items():
        unknown = sorted(set(members) - set(shard_names))
        if unknown:
            raise UserError(f"split {name!r} names shards the dataset does not have: {', '.join(unknown[:3])}")

    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        summary = _write(reader, tmp, salt, splits or {}, CLASSES, progress_bar, progress, clear)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {**summary, "out": str(out)}


def _write(reader, root: Path, salt: str, splits: dict, classes, progress_bar, show: bool, clear: bool) -> dict:
    manifest = reader.manifest
    tables: dict[str, list] = {name: [] for name in TABLES}
    tok = lambda *parts: make_token(salt, *parts)  # noqa: E731
    table_dir = root / VERSION
    table_dir.mkdir(parents=True)
    for channel, _ in CHANNELS.values():
        (root / "samples" / channel).mkdir(parents=True)
    (root / "maps").mkdir()

    for cls in dict.fromkeys(c for c, _ in CLASS_TABLE.values()):
        tables["category"].append({"token": tok("category", cls), "name": cls,
                                   "description": CATEGORY_DESCRIPTIONS[cls]})
    for name, text in ATTRIBUTES.items():
        tables["attribute"].append({"token": tok("attribute", name), "name": name, "description": text})
    for token, level, _, text in VISIBILITY:
        tables["visibility"].append({"token": token, "level": level, "description": text})
    for channel, modality in CHANNELS.values():
        tables["sensor"].append({"token": tok("sensor", channel), "channel": channel, "modality": modality})
    category_of = {cls: tok("category", CLASS_TABLE[cls][0]) for cls in CLASS_TABLE}
    attribute_token = {name: tok("attribute", name) for name in ATTRIBUTES}
    calibrated: dict[str, dict] = {}

    frames_of: dict[str, list[int]] = defaultdict(list)
    for i, (shard, _k) in enumerate(reader.index):
        frames_of[shard].append(i)
    n_bytes, n_radar_points = 0, 0
    bar = progress_bar(total=len(reader), desc="export nuscenes", unit="frame", enabled=show)

    def write_file(rel: str, payload: bytes) -> None:
        nonlocal n_bytes
        (root / rel).write_bytes(payload)
        n_bytes += len(payload)

    for scene_index, shard in enumerate(manifest["shards"]):
        name, frames = shard["name"], frames_of.get(shard["name"], [])
        if not frames:
            continue
        metas = [reader.meta(i) for i in frames]
        sname = scene_name(name)
        log_token, map_token, scene_token = tok("log", name), tok("map", name), tok("scene", name)

        # the log's map: road and sidewalks around the ego's path; the global frame starts at its corner
        path = np.array([np.asarray(m["ego_pose"], float)[:2, 3] for m in metas])
        region = (float(np.floor(path[:, 0].min() - MAP_MARGIN_M)), float(np.floor(path[:, 1].min() - MAP_MARGIN_M)),
                  float(np.ceil(path[:, 0].max() + MAP_MARGIN_M)), float(np.ceil(path[:, 1].max() + MAP_MARGIN_M)))
        offset = np.array([-region[0], -region[1], 0.0])
        mask = map_mask(sequence_road(manifest, shard, frames[0], metas[0]), region)
        write_file(f"maps/{map_token}.png", _png_bytes(mask))
        first = metas[0]
        tables["log"].append({"token": log_token, "logfile": name, "vehicle": f"hydrabench-{first['profile']}",
                              "date_captured": "2020-01-01", "location": f"hydrabench-{first['layout']}"})
        tables["map"].append({"token": map_token, "log_tokens": [log_token], "category": "semantic_prior",
                              "filename": f"maps/{map_token}.png",
                              "hydrabench": {"world_region_m": list(region), "resolution_m": MAP_RESOLUTION_M,
                                             "global_from_world_offset_m": _round(offset, 3)}})

        sample_tokens = [tok("sample", name, k) for k in range(len(frames))]
        prev_sd: dict[str, str] = {}
        sd_rows: dict[str, list[int]] = defaultdict(list)  # channel -> its sample_data rows
        track: dict[int, list[str]] = defaultdict(list)  # actor id -> its annotation tokens, in order
        track_class: dict[int, str] = {}
        annotations = []
        for k, (i, meta) in enumerate(zip(frames, metas)):
            frame = reader[i]
            labels = frame["labels"]
            ts = TIME_BASE_US + scene_index * SCENE_SPACING_US + int(round(meta["timestamp_s"] * 1e6))
            world_from_ego = np.asarray(meta["ego_pose"], float)
            global_from_ego = world_from_ego.copy()
            global_from_ego[:3, 3] += offset
            ego_yaw = math.atan2(world_from_ego[1, 0], world_from_ego[0, 0])
            cal = meta["calibration"]
            tables["sample"].append({
                "token": sample_tokens[k], "timestamp": ts, "scene_token": scene_token,
                "prev": sample_tokens[k - 1] if k else "", "next": sample_tokens[k + 1] if k + 1 < len(frames) else "",
                "hydrabench": {"shard": name, "index": reader.index[i][1], "frame": i, "context": meta["context"],
                               "layout": meta["layout"], "conditions": meta["conditions"],
                               "severity": meta["severity"], "timestamp_s": meta["timestamp_s"],
                               "weather": meta["weather"], "light": meta["light"]}})

            # sensor data: one sample_data, ego pose and (shared when equal) calibrated sensor per sensor
            radar_pts = radar_points(frame["radar_polar"], cal["radar_range_resolution_m"])
            n_radar_points += len(radar_pts)
            for sensor, (channel, modality) in CHANNELS.items():
                if modality == "camera":
                    c = cal[sensor]
                    ego_from_sensor = np.asarray(c["ego_from_camera"], float)
                    intrinsic = [_round(row, 6) for row in c["K"]]
                    rel = f"samples/{channel}/{sname}__{channel}__{ts}.png"
                    payload, fmt, size = _png_bytes(frame[sensor]), "png", (int(c["height"]), int(c["width"]))
                elif modality == "lidar":
                    ego_from_sensor, intrinsic = np.asarray(cal["ego_from_lidar"], float), []
                    rel = f"samples/{channel}/{sname}__{channel}__{ts}.pcd.bin"
                    payload, fmt, size = lidar_bin_bytes(frame["lidar_points"]), "pcd", (0, 0)
                else:
                    ego_from_sensor, intrinsic = np.asarray(cal["ego_from_radar"], float), []
                    rel = f"samples/{channel}/{sname}__{channel}__{ts}.pcd"
                    payload, fmt, size = radar_pcd_bytes(radar_pts), "pcd", (0, 0)
                cs = {"sensor_token": tok("sensor", channel), "translation": _round(ego_from_sensor[:3, 3]),
                      "rotation": quaternion_from_matrix(ego_from_sensor[:3, :3]), "camera_intrinsic": intrinsic}
                cs_token = tok("calibrated_sensor", json.dumps(cs, sort_keys=True))
                if cs_token not in calibrated:
                    calibrated[cs_token] = {"token": cs_token, **cs}
                    tables["calibrated_sensor"].append(calibrated[cs_token])
                sd_token, pose_token = tok("sample_data", name, k, channel), tok("ego_pose", name, k, channel)
                tables["ego_pose"].append({"token": pose_token, "timestamp": ts,
                                           "translation": _round(global_from_ego[:3, 3]),
                                           "rotation": quaternion_from_matrix(global_from_ego[:3, :3])})
                write_file(rel, payload)
                record = {"token": sd_token, "sample_token": sample_tokens[k], "ego_pose_token": pose_token,
                          "calibrated_sensor_token": cs_token, "timestamp": ts, "fileformat": fmt,
                          "is_key_frame": True, "height": size[0], "width": size[1], "filename": rel,
                          "prev": prev_sd.get(channel, ""), "next": ""}
                if channel in prev_sd:
                    tables["sample_data"][sd_rows[channel][-1]]["next"] = sd_token
                sd_rows[channel].append(len(tables["sample_data"]))
                tables["sample_data"].append(record)
                prev_sd[channel] = sd_token

            # annotations: every 3D box of labels["objects"], in the global frame
            obj = labels["objects"]
            lidar_ids, lidar_counts = np.unique(np.asarray(frame["lidar_instance"]), return_counts=True)
            lidar_count = dict(zip(lidar_ids.tolist(), lidar_counts.tolist()))
            radar_xy = (np.column_stack([radar_pts["x"], radar_pts["y"], np.zeros(len(radar_pts))])
                        @ np.asarray(cal["ego_from_radar"], float)[:3, :3].T
                        + np.asarray(cal["ego_from_radar"], float)[:3, 3])[:, :2]
            visible = defaultdict(float)
            for cam in ("camera_left", "camera_right"):
                lab = labels[cam]
                for aid, occ, trunc in zip(lab["ids"], lab["occlusion"], lab["truncation"]):
                    visible[aid] = max(visible[aid], (1.0 - occ) * (1.0 - trunc))
            for j, aid in enumerate(obj["ids"]):
                cls = classes[int(obj["labels"][j]) - 1]
                center, size, yaw = obj["center"][j], obj["size"][j], float(obj["yaw"][j])
                g_center = global_from_ego[:3, :3] @ np.asarray(center, float) + global_from_ego[:3, 3]
                g_yaw = math.atan2(math.sin(yaw + ego_yaw), math.cos(yaw + ego_yaw))
                g_velocity = world_from_ego[:3, :3] @ np.asarray(obj["velocity"][j], float)
                speed = float(np.hypot(g_velocity[0], g_velocity[1]))
                ann_token = tok("sample_annotation", name, k, aid)
                track[aid].append(ann_token)
                track_class[aid] = cls
                annotations.append({
                    "token": ann_token, "sample_token": sample_tokens[k], "instance_token": tok("instance", name, aid),
                    "visibility_token": visibility_level(visible.get(aid, 0.0)),
                    "attribute_tokens": [attribute_token[attribute_of(cls, speed)]],
                    "translation": _round(g_center), "size": _round([size[1], size[0], size[2]]),
                    "rotation": yaw_quaternion(g_yaw), "prev": "", "next": "",
                    "num_lidar_pts": int(lidar_count.get(aid, 0)),
                    "num_radar_pts": int(points_in_footprint(radar_xy, center, size, yaw).sum()),
                    "hydrabench": {"actor_id": int(aid), "class": cls, "velocity": _round(g_velocity[:2]),
                                   "observed": bool(obj["observed"][j]), "range_m": obj["range_m"][j],
                                   "clean_lidar_points": int(obj["lidar_points"][j]),
                                   "clean_radar_cells": int(obj["radar_cells"][j]),
                                   "camera_left_px": int(obj["camera_left_px"][j]),
                                   "camera_right_px": int(obj["camera_right_px"][j])}})
            bar.update(1)

        by_token = {a["token"]: a for a in annotations}
        for aid, chain in track.items():
            for a, b in zip(chain, chain[1:]):
                by_token[a]["next"], by_token[b]["prev"] = b, a
            tables["instance"].append({"token": tok("instance", name, aid), "category_token": category_of[track_class[aid]],
                                       "nbr_annotations": len(chain), "first_annotation_token": chain[0],
                                       "last_annotation_token": chain[-1],
                                       "hydrabench": {"actor_id": int(aid), "class": track_class[aid], "shard": name}})
        tables["sample_annotation"].extend(annotations)
        tables["scene"].append({
            "token": scene_token, "log_token": log_token, "nbr_samples": len(frames),
            "first_sample_token": sample_tokens[0], "last_sample_token": sample_tokens[-1], "name": sname,
            "description": _description(first),
            "hydrabench": {"shard": name, "sequence_id": first["sequence_id"], "context": first["context"],
                           "layout": first["layout"], "conditions": first["conditions"], "severity": first["severity"],
                           "transition": shard.get("transition", "none"), "weather": first["weather"],
                           "light": first["light"], "clear_twin": bool(clear)}})
    bar.close()

    for name in TABLES:
        write_file(f"{VERSION}/{name}.json", _dump(tables[name]))
    split_scenes = {split: [scene_name(s) for s in sorted(set(members))] for split, members in splits.items()}
    write_file(f"{VERSION}/splits.json", _dump(split_scenes))
    counts = {name: len(rows) for name, rows in tables.items()}
    info = {"format": "nuScenes v1.0", "version": VERSION, "dataset_salt": salt,
            "dataset_format_version": manifest["format_version"], "profile": manifest["profile"],
            "frames": len(reader), "labels": counts["sample_annotation"], "radar_points": n_radar_points,
            "clear_twins": bool(clear), "counts": counts,
            "class_table": {c: {"category": v[0], "detection_name": v[1]} for c, v in CLASS_TABLE.items()},
            "channels": {s: c for s, (c, _) in CHANNELS.items()},
            "splits": {split: len(scenes) for split, scenes in split_scenes.items()}}
    write_file("hydrabench_export.json", _dump(info))
    return {**info, "bytes": n_bytes}


# ---------------------------------------------------------------------------------------------
# reading an export back


def load_tables(root: str | Path, version: str = VERSION) -> dict[str, list]:
    """The thirteen tables of an export, as the JSON lists they are (no devkit needed)."""
    return {name: json.loads((Path(root) / version / f"{name}.json").read_text()) for name in TABLES}


def results_from_labels(root: str | Path, *, drop: float = 0.0, offset_m: float = 0.0, seed: int = 0,
                        version: str = VERSION) -> dict:
    """The export's own boxes as a nuScenes detection-results dict, every sample present.

    Written are the boxes the devkit's evaluation scores (num_lidar_pts + num_radar_pts > 0: it
    drops ground truth without a point), each with score 1.0, its detection name (CLASS_TABLE), its
    attribute and its exact velocity. `drop`: the share of them left out, round(drop * n) of each
    detection name's n, chosen by a permutation seeded with `seed`; `offset_m`: every kept box moved
    that far along the global +x axis. Boxes the devkit does not score are never written (a perfect
    detector of what it scores reaches AP 1)."""
    if not 0.0 <= drop <= 1.0:
        raise ValueError(f"drop must be in [0, 1], got {drop}")
    t = load_tables(root, version)
    detection_of = {c["token"]: None for c in t["category"]}
    for cat in t["category"]:
        detection_of[cat["token"]] = next(d for c, d in CLASS_TABLE.values() if c == cat["name"])
    instance_det = {i["token"]: detection_of[i["category_token"]] for i in t["instance"]}
    attribute = {a["token"]: a["name"] for a in t["attribute"]}
    by_name: dict[str, list[dict]] = defaultdict(list)
    for a in t["sample_annotation"]:
        if a["num_lidar_pts"] + a["num_radar_pts"] > 0:
            by_name[instance_det[a["instance_token"]]].append(a)
    results: dict[str, list] = {s["token"]: [] for s in t["sample"]}
    rng = np.random.default_rng(seed)
    for name in sorted(by_name):
        anns = by_name[name]
        keep = np.ones(len(anns), bool)
        keep[rng.permutation(len(anns))[: int(round(drop * len(anns)))]] = False
        for a, kept in zip(anns, keep):
            if kept:
                x, y, z = a["translation"]
                results[a["sample_token"]].append({
                    "sample_token": a["sample_token"], "translation": [x + offset_m, y, z], "size": a["size"],
                    "rotation": a["rotation"], "velocity": a["hydrabench"]["velocity"], "detection_name": name,
                    "detection_score": 1.0,
                    "attribute_name": attribute[a["attribute_tokens"][0]] if a["attribute_tokens"] else ""})
    meta = {"use_camera": False, "use_lidar": False, "use_radar": False, "use_map": False, "use_external": True}
    return {"meta": meta, "results": results}
