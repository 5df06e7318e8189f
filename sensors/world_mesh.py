"""Triangle meshes of the world: static geometry per sequence, actors per frame.

A `MeshSoup` is plain arrays: vertices (V, 3) in the world frame [m], faces (F, 3), and per-vertex
material id and instance index (every face's vertices share both, so per-face values are the
values of its first vertex). Instance index 0 is static geometry; actor k of a frame has index
k + 1 (indices are per frame; `actor_ids[k]` maps back to the simulator's actor id).

Actors get class-specific meshes (a car has a body, a glass cabin, wheels and lights; a truck a cab
and a trailer; two-wheelers are thin with a rider; pedestrians stand upright with legs, torso,
arms and head), built at the class's mean size and scaled per actor.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np
import shapely
import trimesh
from shapely.geometry import MultiPolygon, Polygon, box

from sensors.materials import MATERIAL_ID
from sim.actors import CLASS_SIZE, CLASSES, box_corners_2d
from sim.world import STRUCTURE_ID, Polyline

M = MATERIAL_ID
CURB_HEIGHT = 0.12  # [m] sidewalk above the road
PAINT_LIFT = 0.015  # [m] lane paint above the asphalt
PAINT_WIDTH = 0.15  # [m] lane marking width
DASH, GAP = 3.0, 6.0  # [m] dashed line pattern


@dataclass
class MeshSoup:
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    material: np.ndarray  # (V,) uint8
    instance: np.ndarray  # (V,) int32

    @staticmethod
    def empty() -> MeshSoup:
        return MeshSoup(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int32))

    @staticmethod
    def concat(parts: list[MeshSoup]) -> MeshSoup:
        parts = [p for p in parts if len(p.faces)]
        if not parts:
            return MeshSoup.empty()
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        return MeshSoup(
            np.concatenate([p.vertices for p in parts]),
            np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
            np.concatenate([p.material for p in parts]),
            np.concatenate([p.instance for p in parts]),
        )

    @property
    def face_material(self) -> np.ndarray:
        return self.material[self.faces[:, 0]]

    @property
    def face_instance(self) -> np.ndarray:
        return self.instance[self.faces[:, 0]]


def _soup(vertices: np.ndarray, faces: np.ndarray, material: str, instance: int = 0) -> MeshSoup:
    v = np.asarray(vertices, float)
    return MeshSoup(v, faces, np.full(len(v), M[material], np.uint8), np.full(len(v), instance, np.int32))


@cache
def _unit(kind: str, sections: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Unit primitives built once with trimesh: a cube [-0.5, 0.5]^3, a cylinder of radius 1 and
    height 1 along z centred at the origin, an icosphere of radius 1."""
    if kind == "box":
        m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=sections)
    else:
        m = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def _box(x0, x1, y0, y1, z0, z1, material: str) -> MeshSoup:
    v, f = _unit("box")
    ext = np.array([x1 - x0, y1 - y0, z1 - z0])
    return _soup(v * ext + [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2], f, material)


_AXES = {"z": np.eye(3), "y": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]),
         "x": np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]])}


def _cylinder(radius, length, center, axis: str, material: str, sections: int = 10) -> MeshSoup:
    v, f = _unit("cylinder", sections)
    local = v * [radius, radius, length]
    return _soup(local @ _AXES[axis].T + center, f, material)


def _sphere(radius, center, material: str) -> MeshSoup:
    v, f = _unit("sphere")
    return _soup(v * radius + center, f, material)


def _wheels(xs, half_track, radius, width) -> list[MeshSoup]:
    return [_cylinder(radius, width, (x, s * half_track, radius), "y", "tyre") for x in xs for s in (-1, 1)]


def _lights(length, y_in, y_out, z0, z1) -> list[MeshSoup]:
    parts = []
    for s in (-1, 1):
        ya, yb = sorted((s * y_in, s * y_out))
        parts.append(_box(length / 2 - 0.02, length / 2 + 0.02, ya, yb, z0, z1, "headlight"))
        parts.append(_box(-length / 2 - 0.02, -length / 2 + 0.02, ya, yb, z0 + 0.05, z1 + 0.05, "taillight"))
    return parts


def _pedestrian(height: float = 1.72) -> MeshSoup:
    """A walking adult mid-stride (legs and arms apart), so it fills its 0.5 x 0.6 m class box."""
    s = height / 1.72
    hip, shoulder = 0.86 * s, 1.44 * s

    def limb(x_foot, y0, y1, z0, z1, lean, material):
        # a slanted leg/arm: a box rotated about y around its top (hip/shoulder) joint
        part = _box(-0.06, 0.06, y0, y1, z0, z1, material)
        ang = np.arctan2(x_foot, z1 - z0) * lean
        c, sn = np.cos(ang), np.sin(ang)
        v = part.vertices - [0, 0, z1]
        part.vertices = np.column_stack([c * v[:, 0] + sn * v[:, 2], v[:, 1], -sn * v[:, 0] + c * v[:, 2]]) + [0, 0, z1]
        return part

    parts = [
        limb(0.19, -0.15, -0.03, 0.0, hip, -1.0, "clothing"),
        limb(0.19, 0.03, 0.15, 0.0, hip, 1.0, "clothing"),
        _box(-0.12, 0.12, -0.20, 0.20, hip, shoulder, "clothing"),
        limb(0.14, -0.28, -0.20, 0.86 * s, 1.42 * s, 1.0, "clothing"),
        limb(0.14, 0.20, 0.28, 0.86 * s, 1.42 * s, -1.0, "clothing"),
        _cylinder(0.05, 0.08, (0, 0, 1.48 * s), "z", "skin", 6),
        _sphere(0.11 * s, (0.0, 0.0, 1.61 * s), "skin"),
    ]
    return MeshSoup.concat(parts)


@cache
def class_template(cls: str) -> MeshSoup:
    """Mesh of class `cls` at its mean size, box centre on the ground at the origin, facing +x."""
    L, W, H = CLASS_SIZE[cls][0]
    p: list[MeshSoup] = []
    if cls == "car":
        p += [_box(-L / 2, L / 2, -W / 2, W / 2, 0.30, 0.95, "paint"),
              _box(-1.3, 0.75, -W / 2 + 0.1, W / 2 - 0.1, 0.95, H - 0.08, "car_glass"),
              _box(-1.2, 0.6, -W / 2 + 0.12, W / 2 - 0.12, H - 0.08, H, "paint")]
        p += _wheels((-1.4, 1.4), W / 2 - 0.1, 0.32, 0.22)
        p += _lights(L, 0.5, W / 2 - 0.08, 0.7, 0.85)
    elif cls == "van":
        p += [_box(-L / 2, 1.8, -W / 2, W / 2, 0.35, H, "paint"),
              _box(1.8, L / 2, -W / 2, W / 2, 0.35, 1.1, "paint"),
              _box(1.75, 1.9, -W / 2 + 0.05, W / 2 - 0.05, 1.1, H - 0.25, "car_glass"),
              _box(0.9, 1.8, -W / 2 - 0.01, W / 2 + 0.01, 1.3, 1.9, "car_glass")]
        p += _wheels((-1.7, 1.75), W / 2 - 0.12, 0.36, 0.24)
        p += _lights(L, 0.55, W / 2 - 0.08, 0.75, 0.92)
    elif cls == "truck":
        p += [_box(3.2, L / 2, -W / 2, W / 2, 0.5, 3.2, "paint"),
              _box(L / 2 - 0.06, L / 2 + 0.01, -W / 2 + 0.1, W / 2 - 0.1, 1.8, 2.9, "car_glass"),
              _box(-L / 2, 2.9, -W / 2, W / 2, 1.05, H, "trailer"),
              _box(-L / 2, 2.9, -W / 2 + 0.3, W / 2 - 0.3, 0.5, 1.05, "steel")]
        p += _wheels((4.3, -3.4, -4.6), W / 2 - 0.2, 0.5, 0.35)
        p += _lights(L, 0.7, W / 2 - 0.1, 0.8, 1.0)
    elif cls == "bus":
        p += [_box(-L / 2, L / 2, -W / 2, W / 2, 0.3, H, "paint"),
              _box(-L / 2 + 0.5, L / 2 - 0.5, -W / 2 - 0.01, W / 2 + 0.01, 1.3, 2.6, "car_glass"),
              _box(L / 2 - 0.05, L / 2 + 0.01, -W / 2 + 0.1, W / 2 - 0.1, 1.0, 2.8, "car_glass")]
        p += _wheels((-3.8, 3.8), W / 2 - 0.2, 0.5, 0.3)
        p += _lights(L, 0.7, W / 2 - 0.1, 0.6, 0.8)
    elif cls == "motorbike":
        p += _wheels((-0.72, 0.72), 0.0, 0.3, 0.12)[::2]
        p += [_box(-0.5, 0.6, -0.15, 0.15, 0.40, 0.85, "paint"),
              _box(-0.30, 0.10, -0.20, 0.20, 0.85, 1.25, "clothing"),
              _box(0.10, 0.45, -0.28, 0.28, 0.95, 1.02, "steel"),
              _sphere(0.14, (0.0, 0.0, 1.30), "paint"),
              _box(L / 2 - 0.35, L / 2 - 0.3, -0.08, 0.08, 0.75, 0.85, "headlight")]
    elif cls == "bicycle":
        p += _wheels((-0.52, 0.52), 0.0, 0.34, 0.05)[::2]
        p += [_box(-0.50, 0.50, -0.03, 0.03, 0.40, 0.62, "steel"),
              _box(0.30, 0.40, -0.30, 0.30, 0.98, 1.02, "steel"),
              _box(-0.12, 0.12, -0.12, 0.12, 0.45, 0.95, "clothing"),
              _box(-0.22, 0.18, -0.20, 0.20, 0.95, 1.45, "clothing"),
              _sphere(0.11, (0.0, 0.0, 1.60), "skin")]
    elif cls == "pedestrian":
        p.append(_pedestrian(H))
    else:
        raise ValueError(f"no single template for class {cls!r}")
    soup = MeshSoup.concat(p)
    # normalise to a unit box so per-actor sizes scale it: x, y in [-0.5, 0.5], z in [0, 1]
    soup.vertices = soup.vertices / np.array([L, W, H])
    return soup


def group_template(actor_id: int, members: int, size: np.ndarray) -> MeshSoup:
    """A group of `members` pedestrians spread over the group's footprint (unit-box normalised)."""
    rng = np.random.default_rng(int(actor_id))
    L, W, H = size
    parts = []
    placed: list[np.ndarray] = []
    for _ in range(members):
        for _try in range(30):
            xy = rng.uniform([-L / 2 + 0.25, -W / 2 + 0.3], [L / 2 - 0.25, W / 2 - 0.3])
            # spread towards the footprint's edges, so the group fills its box
            xy = np.sign(xy) * np.maximum(np.abs(xy), rng.uniform(0.3, 1.0) * np.array([L / 2 - 0.25, W / 2 - 0.3]))
            if all(np.linalg.norm(xy - q) > 0.55 for q in placed):
                break
        placed.append(xy)
        ped = _pedestrian(float(np.clip(rng.normal(1.0, 0.05), 0.85, 1.0)) * H)
        yaw = rng.normal(0, 0.4)
        c, s = np.cos(yaw), np.sin(yaw)
        ped.vertices = ped.vertices @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) + [xy[0], xy[1], 0]
        parts.append(ped)
    soup = MeshSoup.concat(parts)
    soup.vertices = soup.vertices / np.array([L, W, H])
    return soup


def actors_mesh(actors, max_range: float | None = None, origin: np.ndarray | None = None,
                index_of=None) -> tuple[MeshSoup, np.ndarray]:
    """Mesh of the actors of one frame; returns (soup, actor_ids).

    Instance indices: `index_of(actor_id)` when given (a per-sequence table, so indices stay
    stable), else k + 1 for the k-th mesh actor, with actor_ids[k] its id. Actors farther than
    `max_range` from `origin` (xy) are left out.
    """
    sel = np.arange(len(actors))
    if max_range is not None and origin is not None and len(actors):
        d = np.linalg.norm(actors.centers[:, :2] - origin[:2], axis=1)
        sel = sel[d < max_range]
    parts, ids = [], []
    names = actors.class_names()
    for k, i in enumerate(sel):
        cls = names[i]
        if cls == "group_of_pedestrians":
            tpl = _group_cached(int(actors.ids[i]), int(actors.members[i]), tuple(np.round(actors.sizes[i], 4)))
        else:
            tpl = class_template(cls)
        size = actors.sizes[i]
        c, s = np.cos(actors.yaws[i]), np.sin(actors.yaws[i])
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        base = actors.centers[i] - np.array([0, 0, size[2] / 2])
        v = (tpl.vertices * size) @ R.T + base
        index = k + 1 if index_of is None else index_of(int(actors.ids[i]))
        parts.append(MeshSoup(v, tpl.faces, tpl.material, np.full(len(v), index, np.int32)))
        ids.append(int(actors.ids[i]))
    return MeshSoup.concat(parts), np.array(ids, np.int64)


@lru_cache(maxsize=4096)
def _group_cached(actor_id: int, members: int, size: tuple) -> MeshSoup:
    return group_template(actor_id, members, np.array(size))


# ---------------------------------------------------------------------------------------------
# static world


def _polys(geom) -> list[Polygon]:
    if geom.is_empty:
        return []
    if isinstance(geom, Polygon):
        return [geom]
    if isinstance(geom, MultiPolygon):
        return list(geom.geoms)
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon)]


TILE_M = 20.0  # flat surfaces are cut into tiles so no triangle spans more than ~20 m


def _tiles(geom, tile: float = TILE_M) -> list:
    """Cut a (Multi)Polygon along a `tile`-metre grid (keeps Embree's BVH and the depth buffer
    well conditioned: long skinny triangles across a 500 m ground make every ray slow)."""
    polys = []
    for poly in _polys(geom):
        x0, y0, x1, y1 = poly.bounds
        if x1 - x0 <= tile and y1 - y0 <= tile:
            polys.append(poly)
            continue
        xs = np.arange(np.floor(x0 / tile) * tile, x1, tile)
        ys = np.arange(np.floor(y0 / tile) * tile, y1, tile)
        cells = shapely.box(*np.meshgrid(xs, ys), *np.meshgrid(xs + tile, ys + tile)).ravel()
        shapely.prepare(poly)
        hit = cells[shapely.intersects(poly, cells)]
        for piece in shapely.intersection(poly, hit):
            polys += [q for q in _polys(piece) if q.area > 1e-6]
    return polys


def _flat(geom, z: float, material: str) -> MeshSoup:
    """Triangulate a (Multi)Polygon into a horizontal surface at height z (normals up)."""
    return _flat_tiles(_tiles(geom), z, material)


def _flat_tiles(tiles: list, z: float, material: str) -> MeshSoup:
    """Triangulate polygons (in order) into one horizontal surface at height z: the same soup as
    `MeshSoup.concat` of `_flat` of each, in one vectorised call."""
    if not tiles:
        return MeshSoup.empty()
    tris = shapely.get_parts(shapely.constrained_delaunay_triangles(np.array(tiles, dtype=object)))
    if len(tris) == 0:
        return MeshSoup.empty()
    coords = shapely.get_coordinates(tris).reshape(len(tris), 4, 2)[:, :3]  # closed rings
    a, b, c = coords[:, 0], coords[:, 1], coords[:, 2]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    faces = np.arange(3 * len(tris)).reshape(-1, 3)
    faces[cross < 0] = faces[cross < 0][:, ::-1]  # counter-clockwise seen from above -> normal +z
    v = coords.reshape(-1, 2)
    return MeshSoup(np.column_stack([v, np.full(len(v), z)]), faces, np.full(len(v), M[material], np.uint8),
                    np.zeros(len(v), np.int32))


def _walls(geom, z0: float, z1: float, material: str) -> MeshSoup:
    """Vertical walls along every ring of a polygon (kerbs)."""
    verts, faces = [], []
    n = 0
    for poly in _polys(geom):
        for ring in [poly.exterior, *poly.interiors]:
            pts = np.asarray(ring.coords)[:, :2]
            for a, b in zip(pts[:-1], pts[1:]):
                verts += [[a[0], a[1], z0], [b[0], b[1], z0], [b[0], b[1], z1], [a[0], a[1], z1]]
                faces += [[n, n + 1, n + 2], [n, n + 2, n + 3], [n, n + 2, n + 1], [n, n + 3, n + 2]]
                n += 4
    if not verts:
        return MeshSoup.empty()
    v = np.array(verts, float)
    return MeshSoup(v, np.array(faces), np.full(len(v), M[material], np.uint8), np.zeros(len(v), np.int32))


def _dashes(ls: shapely.LineString) -> list[shapely.LineString]:
    """`shapely.ops.substring(ls, s, min(s + DASH, length))` for s = 0, DASH + GAP, ... < length,
    with the same coordinates: the end points from `sim.world.Polyline` (GEOS's interpolation, bit
    for bit) and the vertices in between chosen as substring does, by running distances summed in
    Python as ((dx) ** 2 + (dy) ** 2) ** 0.5 (one walk per line instead of one per dash)."""
    length = ls.length
    starts, s = [], 0.0
    while s < length:
        starts.append(s)
        s += DASH + GAP
    ends = [min(a + DASH, length) for a in starts]
    coords = list(ls.coords)
    running, current = [], 0.0  # distance along the line at vertex i (i < last), as substring sums it
    for p1, p2 in zip(coords[:-1], coords[1:]):
        running.append(current)
        current += ((p2[0] - p1[0]) ** 2 + (p2[1] - p1[1]) ** 2) ** 0.5
    line = Polyline(np.asarray(coords))
    first, last = line.points(np.array(starts)).tolist(), line.points(np.array(ends)).tolist()
    out = []
    for a, b, p, q in zip(starts, ends, first, last):
        inner = [coords[i] for i, d in enumerate(running) if a < d < b]
        out.append(shapely.LineString([tuple(p), *inner, tuple(q)]))
    return out


def _stripes(lines: list[np.ndarray], dashed: np.ndarray, z: float) -> MeshSoup:
    """Lane paint: solid lines and DASH / GAP dashes, PAINT_WIDTH wide (flat caps), at height z."""
    segs = []
    for line, d in zip(lines, dashed):
        ls = shapely.LineString(line)
        if ls.length < 0.5:
            continue
        segs += _dashes(ls) if d else [ls]
    if not segs:
        return MeshSoup.empty()
    # BaseGeometry.buffer's defaults (quad_segs=16), which the function form does not share
    polys = shapely.buffer(np.array(segs, dtype=object), PAINT_WIDTH / 2, quad_segs=16, cap_style="flat")
    return _flat_tiles([t for poly in polys for t in _tiles(poly)], z, "lane_paint")


def _clip_lines(lines, dashed, window):
    out, out_dashed = [], []
    for line, d in zip(lines, dashed):
        clipped = shapely.LineString(line).intersection(window)
        for part in getattr(clipped, "geoms", [clipped]):
            if part.geom_type == "LineString" and not part.is_empty and part.length > 0.5:
                out.append(np.asarray(part.coords))
                out_dashed.append(d)
    return out, np.array(out_dashed, bool)


def _zebra(rect: np.ndarray, z: float) -> MeshSoup:
    """Zebra stripes (0.5 m white, 0.5 m gap) across a crosswalk rectangle (4, 2)."""
    a, b, c, d = rect
    along = b - a  # across the road
    n_stripes = int(np.linalg.norm(along) / 1.0)
    tiles = []
    for k in range(n_stripes):
        t0, t1 = k / n_stripes, (k + 0.5) / n_stripes
        q = np.array([a + along * t0, a + along * t1, d + along * t1, d + along * t0])
        tiles += _tiles(Polygon(q))
    return _flat_tiles(tiles, z, "lane_paint")


def _building(c, size, yaw, rng) -> MeshSoup:
    L, W, H = size
    material = ("brick", "concrete", "plaster")[int(rng.integers(3))]
    parts = [_box(-L / 2, L / 2, -W / 2, W / 2, 0.0, H, material)]
    floors = int(H // 3.2)
    for f in range(floors):
        z0, z1 = f * 3.2 + 0.9, f * 3.2 + 2.3
        parts.append(_box(-L / 2 * 0.9, L / 2 * 0.9, -W / 2 - 0.03, W / 2 + 0.03, z0, z1, "window"))
        parts.append(_box(-L / 2 - 0.03, L / 2 + 0.03, -W / 2 * 0.85, W / 2 * 0.85, z0, z1, "window"))
    soup = MeshSoup.concat(parts)
    cy, sy = np.cos(yaw), np.sin(yaw)
    soup.vertices = soup.vertices @ np.array([[cy, sy, 0], [-sy, cy, 0], [0, 0, 1]]) + [c[0], c[1], 0]
    return soup


def _tree(c, size) -> MeshSoup:
    crown, _, H = size
    trunk_h = max(1.5, H - crown)
    return MeshSoup.concat([
        _cylinder(0.12 + 0.02 * crown, trunk_h + 0.3, (c[0], c[1], (trunk_h + 0.3) / 2), "z", "bark", 8),
        _sphere(crown / 2, (c[0], c[1], H - crown / 2), "foliage"),
    ])


def _lamp(c, size, yaw) -> MeshSoup:
    arm, _, H = size
    d = np.array([np.cos(yaw), np.sin(yaw)])
    end = c[:2] + d * arm
    mid = (c[:2] + end) / 2
    parts = [_cylinder(0.08, H, (c[0], c[1], H / 2), "z", "steel", 8)]
    arm_box = _box(-arm / 2, arm / 2, -0.04, 0.04, H - 0.08, H, "steel")
    head = _box(-0.3, 0.3, -0.15, 0.15, H - 0.22, H - 0.08, "lamp_head")
    cy, sy = np.cos(yaw), np.sin(yaw)
    rot = np.array([[cy, sy, 0], [-sy, cy, 0], [0, 0, 1]])
    arm_box.vertices = arm_box.vertices @ rot + [mid[0], mid[1], 0]
    head.vertices = head.vertices @ rot + [end[0], end[1], 0]
    return MeshSoup.concat(parts + [arm_box, head])


def lamp_heads(structures) -> np.ndarray:
    """(N, 3) world positions of street lamp heads (light sources) [m]."""
    sel = structures.kinds == STRUCTURE_ID["street_lamp"]
    out = []
    for c, size, yaw in zip(structures.centers[sel], structures.sizes[sel], structures.yaws[sel]):
        end = c[:2] + np.array([np.cos(yaw), np.sin(yaw)]) * size[0]
        out.append([end[0], end[1], size[2] - 0.25])
    return np.array(out).reshape(-1, 3)


def static_mesh(scene, rng_seed: int = 0, focus=None) -> MeshSoup:
    """Static world of a sequence: ground, road, paint, kerbed sidewalks, zebras, structures.

    `focus`: an optional shapely polygon (e.g. the ego's path buffered by the sensor range); only
    geometry inside it is built.
    """
    rng = np.random.default_rng(rng_seed)
    window = box(*scene.road.region)
    if focus is not None:
        window = window.intersection(focus)
    road = scene.road.road.intersection(window)
    walks = scene.road.sidewalks.intersection(window) if not scene.road.sidewalks.is_empty else scene.road.sidewalks
    paved = shapely.unary_union([road, walks])
    ground = window.difference(paved)
    parts = [
        _flat(ground, 0.0, "grass"),
        _flat(road, 0.0, "asphalt"),
        _stripes(*_clip_lines(scene.road.markings, scene.road.marking_dashed, window), PAINT_LIFT),
    ]
    if not walks.is_empty:
        parts += [_flat(walks, CURB_HEIGHT, "sidewalk"), _walls(walks, 0.0, CURB_HEIGHT, "sidewalk")]
    for cw in scene.road.crosswalks:
        if window.intersects(shapely.Polygon(cw)):
            parts.append(_zebra(np.asarray(cw), PAINT_LIFT))
    st = scene.structures
    if focus is not None and len(st):
        reach = np.maximum(st.sizes[:, 0], st.sizes[:, 1])
        inside = shapely.dwithin(window, shapely.points(st.centers[:, :2]), reach)
        st = st[inside]
    for kind, c, size, yaw in zip(st.kinds, st.centers, st.sizes, st.yaws):
        if kind == STRUCTURE_ID["building"]:
            parts.append(_building(c, size, yaw, rng))
        elif kind == STRUCTURE_ID["tree"]:
            parts.append(_tree(c, size))
        elif kind == STRUCTURE_ID["guardrail"]:
            corners = box_corners_2d(c[None, :2], size[None, :2], np.array([yaw]))[0]
            seg = MeshSoup.concat([_box(-size[0] / 2, size[0] / 2, -0.1, 0.1, 0.45, 0.8, "steel"),
                                   _box(-0.05, 0.05, -0.06, 0.06, 0.0, 0.45, "steel")])
            cy, sy = np.cos(yaw), np.sin(yaw)
            seg.vertices = seg.vertices @ np.array([[cy, sy, 0], [-sy, cy, 0], [0, 0, 1]]) + [c[0], c[1], 0]
            del corners
            parts.append(seg)
        elif kind == STRUCTURE_ID["street_lamp"]:
            parts.append(_lamp(c, size, yaw))
    return MeshSoup.concat(parts)


__all__ = ["MeshSoup", "actors_mesh", "class_template", "static_mesh", "lamp_heads", "CLASSES"]
