"""Matplotlib figures (Agg backend, written to files)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402
from matplotlib.patches import Polygon as MplPolygon  # noqa: E402

from sim.actors import CLASSES, box_corners_2d  # noqa: E402
from sim.world import STRUCTURE_ID  # noqa: E402
from study.numbers import number_text
from study.outputs import savefig_atomic  # noqa: E402

CLASS_COLORS = {
    "car": "#1f77b4",
    "van": "#17becf",
    "truck": "#d62728",
    "bus": "#ff7f0e",
    "motorbike": "#9467bd",
    "bicycle": "#e377c2",
    "pedestrian": "#2ca02c",
    "group_of_pedestrians": "#bcbd22",
}


def _polys(geom):
    if geom.is_empty:
        return []
    return list(geom.geoms) if hasattr(geom, "geoms") else [geom]


def _fill(ax, geom, **kw):
    for poly in _polys(geom):
        if poly.geom_type != "Polygon":
            continue
        ax.add_patch(MplPolygon(np.asarray(poly.exterior.coords), closed=True, **kw))
        for hole in poly.interiors:
            ax.add_patch(MplPolygon(np.asarray(hole.coords), closed=True, facecolor="#d9e8c8", edgecolor="none"))


def draw_topdown(ax, scene, half_extent: float = 70.0) -> None:
    """Top-down view of a Scene centred on the ego, world axes (x east, y north)."""
    ex, ey = scene.ego.position[:2]
    ax.set_facecolor("#d9e8c8")
    _fill(ax, scene.road.sidewalks, facecolor="#c8c3b8", edgecolor="none")
    _fill(ax, scene.road.road, facecolor="#6e6e6e", edgecolor="none")
    for cw in scene.road.crosswalks:
        ax.add_patch(MplPolygon(cw, closed=True, facecolor="white", edgecolor="none", alpha=0.8, hatch="||"))
    for line, dashed in zip(scene.road.markings, scene.road.marking_dashed):
        ax.plot(line[:, 0], line[:, 1], color="white", lw=0.6, ls=(0, (3, 4)) if dashed else "-")
    st = scene.structures
    near = np.linalg.norm(st.centers[:, :2] - [ex, ey], axis=1) < half_extent * 1.6
    for k, c, s, yaw in zip(st.kinds[near], st.centers[near], st.sizes[near], st.yaws[near]):
        if k == STRUCTURE_ID["building"]:
            corners = box_corners_2d(c[None, :2], s[None, :2], np.array([yaw]))[0]
            ax.add_patch(MplPolygon(corners, closed=True, facecolor="#a0785a", edgecolor="#5a3e2b", lw=0.5))
        elif k == STRUCTURE_ID["tree"]:
            ax.add_patch(Circle(c[:2], s[0] / 2, facecolor="#3f7f3f", edgecolor="none", alpha=0.8))
        elif k == STRUCTURE_ID["guardrail"]:
            corners = box_corners_2d(c[None, :2], s[None, :2], np.array([yaw]))[0]
            ax.add_patch(MplPolygon(corners, closed=True, facecolor="#333333", edgecolor="none"))
        elif k == STRUCTURE_ID["street_lamp"]:
            lit = scene.light.street_lamps_on
            ax.add_patch(Circle(c[:2], 0.6, facecolor="#ffd700" if lit else "#444444", edgecolor="k", lw=0.3))
    a = scene.actors
    names = a.class_names()
    corners = a.footprints()
    for i in range(len(a)):
        color = CLASS_COLORS[names[i]]
        ax.add_patch(
            MplPolygon(corners[i], closed=True, facecolor=color, edgecolor="k", lw=0.4,
                       alpha=0.55 if a.parked[i] else 0.95)
        )
        if not a.parked[i] and np.linalg.norm(a.velocities[i]) > 0.1:
            c = a.centers[i, :2]
            d = np.array([np.cos(a.yaws[i]), np.sin(a.yaws[i])]) * max(a.sizes[i, 0] * 0.5, 0.6)
            ax.plot([c[0], c[0] + d[0]], [c[1], c[1] + d[1]], color="k", lw=0.6)
    ego = box_corners_2d(np.array([[ex, ey]]), scene.ego.size[None, :2], np.array([scene.ego.yaw]))[0]
    ax.add_patch(MplPolygon(ego, closed=True, facecolor="black", edgecolor="yellow", lw=1.0))
    # camera field of view (90 deg, ZED-like) as a hint of where the sensors look
    yaw = scene.ego.yaw
    for da in (-np.pi / 4, np.pi / 4):
        ax.plot([ex, ex + 60 * np.cos(yaw + da)], [ey, ey + 60 * np.sin(yaw + da)], color="yellow", lw=0.5, ls=":")
    ax.set_xlim(ex - half_extent, ex + half_extent)
    ax.set_ylim(ey - half_extent, ey + half_extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")


def weather_title(scene) -> str:
    w = scene.weather
    parts = [f"{scene.context.name} (layout {scene.context.layout}), severity {scene.severity}"]
    parts.append(
        f"visibility {w.visibility_m:,.0f} m, rain {w.rain_mm_h:.1f} mm/h, snow {w.snow_mm_h:.2f} mm/h, "
        f"film {w.water_film_mm:.2f} mm"
    )
    parts.append(
        f"illuminance {w.illuminance_lux:,.3g} lx (sun {scene.light.sun_elevation_deg:.0f} deg), lens "
        f"{w.lens_coverage_pct[0]:.0f}/{w.lens_coverage_pct[1]:.0f} %, t = {scene.timestamp_s:.1f} s"
    )
    return "\n".join(parts)


def plot_scene(scene, path: str, half_extent: float = 70.0) -> None:
    fig, ax = plt.subplots(figsize=(8, 8.6), dpi=110)
    draw_topdown(ax, scene, half_extent)
    ax.set_title(weather_title(scene), fontsize=8.5)
    handles = [plt.Line2D([], [], marker="s", ls="", color=CLASS_COLORS[c], label=c) for c in CLASSES]
    handles.append(plt.Line2D([], [], marker="s", ls="", color="black", mec="yellow", label="ego"))
    ax.legend(handles=handles, loc="lower left", fontsize=7, ncol=3, framealpha=0.8)
    fig.tight_layout()
    savefig_atomic(fig, path)
    plt.close(fig)


def _draw_boxes(ax, boxes, labels, difficult, lw=1.0):
    from matplotlib.patches import Rectangle

    for b, lab, d in zip(boxes, labels, difficult):
        color = CLASS_COLORS[CLASSES[int(lab) - 1]]
        ax.add_patch(Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], fill=False, edgecolor=color, lw=lw,
                               ls="--" if d else "-"))


def _rotated(ax, rotated, labels, difficult):
    for (cx, cy, length, width, ang), lab, d in zip(rotated, labels, difficult):
        # image axes: up = forward; the box's length lies along `ang` ccw from up
        fwd = np.array([-np.sin(ang), -np.cos(ang)])
        left = np.array([-np.cos(ang), np.sin(ang)])
        c = np.array([cx, cy])
        pts = np.array([c + fwd * length / 2 + left * width / 2, c + fwd * length / 2 - left * width / 2,
                        c - fwd * length / 2 - left * width / 2, c - fwd * length / 2 + left * width / 2])
        ax.add_patch(MplPolygon(pts, closed=True, fill=False, edgecolor=CLASS_COLORS[CLASSES[int(lab) - 1]],
                                lw=0.9, ls="--" if d else "-"))


def frame_caption(meta: dict) -> str:
    w = meta["weather"]
    lines = [
        f"{meta['context']} (layout {meta['layout']}), severity {meta['severity']}, sequence {meta['sequence_id']} "
        f"frame {meta['frame_index']}, t = {meta['timestamp_s']:.1f} s, profile {meta['profile']}",
        f"visibility {w['visibility_m']:,.0f} m (fog {w['fog_visibility_m']:,.0f} m), rain {w['rain_mm_h']} mm/h, "
        f"snow {w['snow_mm_h']} mm/h, water film {w['water_film_mm']} mm, {w['illuminance_lux']:.3g} lx, "
        f"lens cover {w['lens_coverage_pct']} %",
    ]
    deg = meta.get("degradation") or {}
    if deg:
        parts = []
        for name, params in deg.items():
            if isinstance(params, dict) and set(params) <= {"camera_left", "camera_right"}:
                cams = "/".join("L" if c == "camera_left" else "R" for c in params)
                first = next(iter(params.values()))
                shown = ", ".join(f"{k}={number_text(v)}" for k, v in first.items() if not isinstance(v, list | dict) and k != "seed")
                parts.append(f"{name}[{cams}]({shown})")
            elif isinstance(params, dict):
                shown = ", ".join(f"{k}={number_text(v)}" for k, v in params.items() if not isinstance(v, list | dict) and k != "seed")
                parts.append(f"{name}({shown})")
            else:
                parts.append(f"{name}={number_text(params)}")
        text = "degradation: " + "; ".join(parts)
        lines += [text[i:i + 200] for i in range(0, len(text), 200)]
    else:
        lines.append("degradation: none")
    return "\n".join(lines)



def plot_frame(frame: dict, path: str) -> None:
    """All sensors of one stored frame with their labels and a caption (for `hydrabench show`)."""
    meta, labels = frame["meta"], frame["labels"]
    fig = plt.figure(figsize=(15, 8.6), dpi=100)
    gs = fig.add_gridspec(2, 6, height_ratios=[1.0, 1.45])
    axes = [fig.add_subplot(gs[0, 0:3]), fig.add_subplot(gs[0, 3:6]), fig.add_subplot(gs[1, 0:2]),
            fig.add_subplot(gs[1, 2:4]), fig.add_subplot(gs[1, 4:6])]
    for ax, name in zip(axes[:2], ("camera_left", "camera_right")):
        ax.imshow(frame[name], interpolation="nearest")
        lab = labels[name]
        _draw_boxes(ax, lab["boxes"], lab["labels"], lab["difficult"])
        ax.set_title(f"{name} ({len(lab['boxes'])} boxes, dashed = difficult)", fontsize=9)
    bev = labels["bev"]
    axes[2].imshow(frame["lidar_bev"], interpolation="nearest")
    _rotated(axes[2], bev["rotated"], bev["labels"], bev["difficult"])
    axes[2].set_title("lidar BEV (height, density, intensity) + BEV boxes", fontsize=9)
    radar = np.asarray(frame["radar_bev"], float)
    axes[3].imshow(np.clip((radar - 15) / 90, 0, 1), cmap="gray", interpolation="nearest")
    _rotated(axes[3], bev["rotated"], bev["labels"], bev["difficult"])
    axes[3].set_title("radar BEV (0.5 dB/count, stretched)", fontsize=9)
    axes[4].imshow(frame["fwd_lidar"], interpolation="nearest")
    lab = labels["camera_right"]
    _draw_boxes(axes[4], lab["boxes"], lab["labels"], lab["difficult"], lw=0.7)
    axes[4].set_title("forward lidar in camera_right (closeness, intensity, height)", fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    handles = [plt.Line2D([], [], color=CLASS_COLORS[c], lw=2, label=c) for c in CLASSES]
    fig.legend(handles=handles, loc="lower center", ncol=8, fontsize=8, frameon=False)
    caption = frame_caption(meta)
    fig.suptitle(caption, fontsize=8.5, x=0.01, ha="left", y=0.995, va="top")
    top = 1.0 - 0.022 * (caption.count("\n") + 1)
    fig.tight_layout(rect=(0, 0.03, 1, top))
    savefig_atomic(fig, path)
    plt.close(fig)


def _weather_label(cond: str, sev: int, w) -> str:
    if cond == "clear":
        return "clear (severity 0)"
    if cond == "fog":
        q = f"visibility {w.fog_visibility_m:.0f} m"
    elif cond == "rain":
        q = f"{w.rain_mm_h:.1f} mm/h"
    elif cond == "snow":
        q = f"{w.snow_mm_h:.2f} mm/h"
    else:
        q = f"{w.illuminance_lux:.3g} lx"
    return f"{cond} {sev}\n{q}"


def plot_gallery(panels: list, path: str, title: str = "") -> None:
    """Rows of (condition, severity), columns: right camera, forward lidar, lidar BEV, radar BEV."""
    n = len(panels)
    fig, axes = plt.subplots(n, 4, figsize=(13, 1.95 * n), dpi=70,
                             gridspec_kw={"width_ratios": [1.79, 1.79, 1, 1]})
    axes = np.atleast_2d(axes)
    cols = ("camera_right", "forward lidar", "lidar BEV", "radar BEV")
    for r, p in enumerate(panels):
        fr = p["frame"]
        S = fr.lidar_bev.shape[0]
        c0, c1 = S // 4, 3 * S // 4  # central half of the BEV: +-25 m at the cpu profile
        imgs = [fr.camera_right, fr.fwd_lidar, fr.lidar_bev[c0:c1, c0:c1],
                np.clip((fr.radar_bev[c0:c1, c0:c1].astype(float) - 15) / 90, 0, 1)]
        for c, (ax, img) in enumerate(zip(axes[r], imgs)):
            ax.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest", aspect="auto")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=10)
        axes[r, 0].set_ylabel(_weather_label(p["condition"], p["severity"], p["weather"]), fontsize=9,
                              rotation=0, ha="right", va="center")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0.04, 0, 1, 0.995 if not title else 1 - 0.6 / (1.95 * n)))
    savefig_atomic(fig, path)
    plt.close(fig)


def plot_training_curves(metrics_csv: str | Path, path: str | Path) -> None:
    """A training run's metrics.csv as two panels against the epoch: mean training loss per branch,
    and test mAP@0.5 per branch (in its own frame) and of their late fusion."""
    import csv

    with open(metrics_csv) as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise ValueError(f"{metrics_csv} has no epochs")
    epochs = [int(r["epoch"]) for r in rows]

    def series(key):
        return [float(r[key]) if r.get(key) not in (None, "", "None") else np.nan for r in rows]  # no test split: None

    fig, (ax_l, ax_m) = plt.subplots(1, 2, figsize=(10, 3.6))
    for key in rows[-1]:
        if key.startswith("loss_") and key != "loss_total":
            ax_l.plot(epochs, series(key), marker="o", ms=3, label=key[5:])
        if key.startswith("map_"):
            name = key[4:]
            ax_m.plot(epochs, series(key), marker="o", ms=3, label=name,
                      **({"color": "k", "ls": "--"} if name == "fused" else {}))
    ax_l.set(xlabel="epoch", ylabel="mean training loss", title="training loss per branch")
    ax_m.set(xlabel="epoch", ylabel="test mAP@0.5 (VOC)", title="test mAP per branch", ylim=(0, None))
    for ax in (ax_l, ax_m):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    savefig_atomic(fig, path, dpi=110)
    plt.close(fig)
