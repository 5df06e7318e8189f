"""Static world: road geometry from a highway-env network, and static structures.

Everything here is in the world frame of `sim.actors` (x east, y north, z up, metres).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np
import shapely
import shapely.affinity
import shapely.ops
from shapely.geometry import LineString, MultiLineString, MultiPolygon, Polygon, box
from shapely.ops import unary_union

STRUCTURE_KINDS: tuple[str, ...] = ("building", "tree", "guardrail", "street_lamp")
STRUCTURE_ID = {k: i for i, k in enumerate(STRUCTURE_KINDS)}


def hw_to_world(xy: np.ndarray) -> np.ndarray:
    """highway-env plane (x right, y down) -> world (x east, y north): (x, y) -> (x, -y)."""
    xy = np.asarray(xy, dtype=float)
    return xy * np.array([1.0, -1.0])


@dataclass(frozen=True)
class RoadGeometry:
    """Road layout of a sequence (shared by all its frames).

    Fields:
        lanes: lane centre polylines, each (M, 2) [m], in driving direction.
        lane_widths: (L,) lane widths [m].
        markings: painted line polylines, each (K, 2) [m].
        marking_dashed: (len(markings),) bool, dashed (True) or solid line.
        road: drivable surface incl. parking strips (shapely (Multi)Polygon) [m].
        sidewalks: pedestrian surface beside the road (shapely (Multi)Polygon, may be empty) [m].
        crosswalks: zebra crossings, each a (4, 2) rectangle [m].
        crossing_paths: where pedestrians walk across, each (2, 2) segment [m] (one per crosswalk).
        walk_paths: sidewalk centre lines pedestrians follow, each (K, 2) [m].
        region: (xmin, ymin, xmax, ymax) of the area the geometry was built for [m].
    """

    lanes: tuple[np.ndarray, ...]
    lane_widths: np.ndarray
    markings: tuple[np.ndarray, ...]
    marking_dashed: np.ndarray
    road: Polygon | MultiPolygon
    sidewalks: Polygon | MultiPolygon
    crosswalks: tuple[np.ndarray, ...]
    crossing_paths: tuple[np.ndarray, ...]
    walk_paths: tuple[np.ndarray, ...]
    region: tuple[float, float, float, float]
    _prepared: dict = field(default_factory=dict, compare=False, repr=False)

    def fingerprint(self) -> bytes:
        """Bytes that change whenever the geometry changes (for determinism hashing)."""
        parts = [np.concatenate(self.lanes).round(6).tobytes(), self.lane_widths.tobytes()]
        parts += [shapely.to_wkb(self.road), shapely.to_wkb(self.sidewalks)]
        parts += [c.round(6).tobytes() for c in self.crosswalks]
        return b"".join(parts)

    def on_sidewalk_or_crossing(self, xy: np.ndarray, tol: float = 0.3) -> np.ndarray:
        """(N,) bool: points inside a sidewalk or a crosswalk (with tolerance) [m]."""
        key = ("walkable", tol)
        if key not in self._prepared:
            walk = unary_union([self.sidewalks] + [Polygon(c) for c in self.crosswalks]).buffer(tol)
            shapely.prepare(walk)
            self._prepared[key] = walk
        return shapely.contains_xy(self._prepared[key], xy[:, 0], xy[:, 1])

    def on_road(self, xy: np.ndarray) -> np.ndarray:
        if "road" not in self._prepared:
            r = self.road
            shapely.prepare(r)
            self._prepared["road"] = r
        return shapely.contains_xy(self._prepared["road"], xy[:, 0], xy[:, 1])


@dataclass(frozen=True)
class Structures:
    """Static structures of a sequence, S rows (columnar).

    Fields:
        kinds: (S,) int64 index into `STRUCTURE_KINDS`.
        centers: (S, 3) footprint centre at ground level (z = 0) [m].
        sizes: (S, 3) (length, width, height) [m]; a tree's length/width is its crown diameter,
            a street lamp's length is its arm reach over the road.
        yaws: (S,) orientation of the length axis, ccw from +x [rad]; a lamp's arm points along it.
    """

    kinds: np.ndarray
    centers: np.ndarray
    sizes: np.ndarray
    yaws: np.ndarray

    def __len__(self) -> int:
        return len(self.kinds)

    def __getitem__(self, index) -> Structures:
        return Structures(self.kinds[index], self.centers[index], self.sizes[index], self.yaws[index])

    @staticmethod
    def from_rows(rows: list[tuple[str, float, float, float, float, float, float]]) -> Structures:
        """rows of (kind, x, y, length, width, height, yaw)."""
        if not rows:
            return Structures(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        kinds = np.array([STRUCTURE_ID[r[0]] for r in rows], np.int64)
        arr = np.array([r[1:] for r in rows], float)
        centers = np.column_stack([arr[:, 0], arr[:, 1], np.zeros(len(rows))])
        return Structures(kinds, centers, arr[:, 2:5], arr[:, 5])

    def count(self, kind: str) -> int:
        return int((self.kinds == STRUCTURE_ID[kind]).sum())

    def fingerprint(self) -> bytes:
        return self.kinds.tobytes() + self.centers.round(6).tobytes() + self.sizes.round(6).tobytes()


# ---------------------------------------------------------------------------------------------
# geometry extraction


def _sample_lane(lane, step: float, lateral: float = 0.0) -> np.ndarray:
    """Points every <= `step` m along a lane at offset `lateral` (world frame).

    A straight lane's points are computed in one array expression: the same float64 products and
    sums as `StraightLane.position`, element by element, so the same bits (tests/sim/test_world.py).
    Other lanes (arcs, polylines) go point by point through their own `position`."""
    from highway_env.road.lane import StraightLane

    n = max(2, int(np.ceil(lane.length / step)) + 1)
    s = np.linspace(0.0, lane.length, n)
    if type(lane) is StraightLane:
        pts = lane.start + s[:, None] * lane.direction + lateral * lane.direction_lateral
    else:
        pts = np.array([lane.position(si, lateral) for si in s])
    return hw_to_world(pts)


def lines_of(geom) -> list[np.ndarray]:
    """All line strings of a (Multi)LineString / GeometryCollection as (K, 2) arrays."""
    if geom.is_empty:
        return []
    if isinstance(geom, LineString):
        return [np.asarray(geom.coords)[:, :2]]
    if isinstance(geom, MultiLineString) or hasattr(geom, "geoms"):
        out = []
        for g in geom.geoms:
            out += lines_of(g)
        return out
    return []


def extract_road(
    network,
    region: tuple[float, float, float, float],
    *,
    parking_width: float = 0.0,
    sidewalk_offset: float | None = None,
    sidewalk_width: float = 3.0,
    crossings: list[np.ndarray] | None = None,
    step: float = 2.0,
) -> RoadGeometry:
    """Road geometry of a highway-env RoadNetwork within `region`.

    Args:
        network: highway_env RoadNetwork.
        region: (xmin, ymin, xmax, ymax) world window to keep [m].
        parking_width: strip added beside the outer lanes for parked cars [m].
        sidewalk_offset: distance from the road edge to the sidewalk's inner edge [m]; None = no
            sidewalk (motorway).
        sidewalk_width: sidewalk width [m].
        crossings: (2, 2) centre segments of crosswalks (world) [m].
    """
    from highway_env.road.lane import LineType

    window = box(*region)
    lanes, widths, markings, dashed, strips = [], [], [], [], []
    for _from, tos in network.graph.items():
        for _to, lane_list in tos.items():
            for lane in lane_list:
                w = float(lane.width_at(0.0))
                centre = _sample_lane(lane, step)
                line = LineString(centre)
                if not line.intersects(window):
                    continue
                lanes.append(centre)
                widths.append(w)
                left = _sample_lane(lane, step, -w / 2)
                right = _sample_lane(lane, step, w / 2)
                strips.append(Polygon(np.vstack([left, right[::-1]])).buffer(0.05))
                for side, pts in ((0, left), (1, right)):
                    lt = lane.line_types[side] if lane.line_types else LineType.NONE
                    if lt in (LineType.CONTINUOUS, LineType.CONTINUOUS_LINE, LineType.STRIPED):
                        markings.append(pts)
                        dashed.append(lt == LineType.STRIPED)
    lanes_union = unary_union(strips)
    road = lanes_union.buffer(parking_width, join_style="mitre") if parking_width > 0 else lanes_union
    road = road.intersection(window)
    # Markings clipped to the window; markings of the same line drawn by two lanes coincide
    # (harmless for rendering).
    kept_marks, kept_dashed = [], []
    for pts, d in zip(markings, dashed):
        for part in lines_of(LineString(pts).intersection(window)):
            kept_marks.append(part)
            kept_dashed.append(d)
    crosswalks, crossing_paths, walk_paths = [], [], []
    sidewalks = Polygon()
    if sidewalk_offset is not None:
        inner = road.buffer(sidewalk_offset)
        outer = road.buffer(sidewalk_offset + sidewalk_width)
        sidewalks = outer.difference(inner).intersection(window)
        mid = road.buffer(sidewalk_offset + sidewalk_width / 2).boundary.intersection(window)
        walk_paths = [p for p in lines_of(mid) if len(p) >= 2 and LineString(p).length > 5.0]
        for seg in crossings or []:
            seg = np.asarray(seg, float)
            d = seg[1] - seg[0]
            n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
            half = 1.5  # a 3 m wide zebra crossing
            rect = np.array([seg[0] - n * half, seg[1] - n * half, seg[1] + n * half, seg[0] + n * half])
            if Polygon(rect).intersects(window):
                crosswalks.append(rect)
                crossing_paths.append(seg)
    return RoadGeometry(
        lanes=tuple(lanes),
        lane_widths=np.array(widths),
        markings=tuple(kept_marks),
        marking_dashed=np.array(kept_dashed, bool),
        road=road,
        sidewalks=sidewalks,
        crosswalks=tuple(crosswalks),
        crossing_paths=tuple(crossing_paths),
        walk_paths=tuple(walk_paths),
        region=tuple(float(v) for v in region),
    )


# ---------------------------------------------------------------------------------------------
# structure placement helpers


def _tangents(line: np.ndarray) -> np.ndarray:
    d = np.gradient(line, axis=0)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


class Polyline:
    """A polyline (K >= 2, 2) [m] and the running segment lengths GEOS uses to find a point at a
    distance along it: `points` and `point` equal `shapely.line_interpolate_point(LineString(line),
    distance)` bit for bit, for finite distances (negative ones count from the end).

    GEOS (LengthLocationMap) walks the segments adding up their lengths sqrt(dx*dx + dy*dy) one
    by one, stops at the first segment whose running total exceeds the distance and returns
    p0 + (p1 - p0) * frac, frac = (distance - total before it) / its length (p0 for frac <= 0, p1
    for frac >= 1); 0 or less gives the first vertex, the length or more the last. The same float
    operations: np.cumsum adds in GEOS's order, and `point` repeats them on Python floats (the
    same IEEE doubles) for one distance without numpy's per-call overhead.
    """

    def __init__(self, line: np.ndarray) -> None:
        xy = np.asarray(line, float)
        self.xy = xy
        self.p0, self.p1 = xy[:-1], xy[1:]
        self.d = self.p1 - self.p0
        self.seg = np.sqrt(self.d[:, 0] * self.d[:, 0] + self.d[:, 1] * self.d[:, 1])
        self.total = np.cumsum(self.seg)
        self.before = np.concatenate([[0.0], self.total[:-1]])
        self._rows = None

    def points(self, distances: np.ndarray) -> np.ndarray:
        """(N, 2) points at `distances` along the line [m]."""
        distances = np.asarray(distances, float)
        distances = np.where(distances < 0, self.total[-1] + distances, distances)  # from the end
        i = np.searchsorted(self.total, distances, side="right")  # first segment with total > distance
        out = np.empty((len(distances), 2))
        out[:] = self.xy[-1]  # at or past the end
        inside = (i < len(self.seg)) & (distances > 0)
        k = i[inside]
        frac = ((distances[inside] - self.before[k]) / self.seg[k])[:, None]
        out[inside] = np.where(frac <= 0, self.p0[k], np.where(frac >= 1, self.p1[k], self.d[k] * frac + self.p0[k]))
        out[distances <= 0] = self.xy[0]
        return out

    def point(self, distance: float) -> np.ndarray:
        """(2,) point at one `distance` along the line [m] (same bits as `points`)."""
        if self._rows is None:
            self._rows = (self.total.tolist(), self.before.tolist(), self.seg.tolist(), self.xy.tolist())
        total, before, seg, xy = self._rows
        if distance < 0:  # measured from the end
            distance = total[-1] + distance
        if distance <= 0:
            return np.array(xy[0])
        i = bisect.bisect_right(total, distance)
        if i >= len(seg):
            return np.array(xy[-1])
        frac = (distance - before[i]) / seg[i]
        (x0, y0), (x1, y1) = xy[i], xy[i + 1]
        if frac <= 0:
            return np.array((x0, y0))
        if frac >= 1:
            return np.array((x1, y1))
        return np.array(((x1 - x0) * frac + x0, (y1 - y0) * frac + y0))


def resample(line: np.ndarray, step: float) -> np.ndarray:
    """Points every ~`step` metres along a polyline (end points included)."""
    ls = LineString(line)
    n = max(2, int(ls.length / step) + 1)
    return Polyline(line).points(np.linspace(0, ls.length, n))


def ring_lines(geom, offset: float, window: Polygon) -> list[np.ndarray]:
    """Lines at `offset` metres outside the boundary of `geom`, clipped to the window."""
    return lines_of(geom.buffer(offset).boundary.intersection(window))


def distance_to_area(area, xy: np.ndarray) -> np.ndarray:
    """(N,) `shapely.distance(area, shapely.points(xy))` for a (Multi)Polygon `area`, bit for bit,
    without measuring every point against every boundary segment.

    GEOS's point-polygon distance is 0 for a point inside or on the area, else the smallest
    point-segment distance over all boundary segments. Here each point meets only the segments
    within an upper bound of that smallest distance (its distance to the nearest vertex of the
    boundary resampled every 2 m, found with a k-d tree); GEOS measures those few (the same
    point-segment computation) and the smallest is kept. Other geometry types go to shapely.
    `area` is prepared (shapely.prepare) for the inside test.
    """
    from scipy.spatial import cKDTree

    points = shapely.points(xy)
    if area.is_empty or not isinstance(area, Polygon | MultiPolygon) or len(xy) == 0:
        return shapely.distance(area, points)
    rings = shapely.get_rings(shapely.get_parts(area))
    coords = [shapely.get_coordinates(r) for r in rings]
    segments = shapely.linestrings(np.concatenate([np.stack([c[:-1], c[1:]], axis=1) for c in coords]))
    vertices = shapely.get_coordinates(shapely.segmentize(rings, 2.0))
    bound, _ = cKDTree(vertices).query(xy)
    bound = bound * (1 + 1e-9) + 1e-6  # never below the true smallest distance
    x, y = xy[:, 0], xy[:, 1]
    point_index, segment_index = shapely.STRtree(segments).query(
        shapely.box(x - bound, y - bound, x + bound, y + bound)
    )
    out = np.full(len(xy), np.inf)
    np.minimum.at(out, point_index, shapely.distance(points[point_index], segments[segment_index]))
    shapely.prepare(area)
    out[shapely.intersects_xy(area, x, y)] = 0.0
    return out


def outward_normals(line: np.ndarray, avoid) -> np.ndarray:
    """Unit normals of a polyline pointing away from geometry `avoid` (e.g. the road)."""
    t = _tangents(line)
    n = np.column_stack([-t[:, 1], t[:, 0]])
    probe = line + n * 1.0
    dist = distance_to_area(avoid, np.vstack([probe, line]))
    dist_plus, dist_here = dist[: len(line)], dist[len(line):]
    flip = dist_plus < dist_here
    n[flip] *= -1
    return n


def place_buildings(
    rng: np.random.Generator,
    road,
    window: Polygon,
    *,
    clearance: float,
    depth: tuple[float, float] = (8.0, 20.0),
    frontage: tuple[float, float] = (8.0, 25.0),
    height: tuple[float, float] = (6.0, 25.0),
    gap: tuple[float, float] = (1.0, 12.0),
    keep_clear=None,
) -> list[tuple]:
    """Rows of buildings along the road, set back `clearance` m from the road edge.

    Footprints are oriented with the road, never overlap each other, the road buffer or
    `keep_clear` (a shapely geometry).
    """
    rows, placed = [], []
    forbidden = road.buffer(clearance - 0.05)
    if keep_clear is not None:
        forbidden = forbidden.union(keep_clear)
    shapely.prepare(forbidden)
    for line in ring_lines(road, clearance, window):
        if LineString(line).length < 10:
            continue
        pts = resample(line, 1.0)
        normals = outward_normals(pts, road)
        tangents = _tangents(pts)
        s = rng.uniform(0, gap[1])
        while s < len(pts) - 1:
            i = int(s)
            w = rng.uniform(*frontage)
            dep = rng.uniform(*depth)
            h = rng.uniform(*height)
            c = pts[i] + normals[i] * (dep / 2 + rng.uniform(0.0, 2.0)) + tangents[i] * w / 2
            yaw = float(np.arctan2(tangents[i, 1], tangents[i, 0]))
            fp = shapely.affinity.rotate(
                box(-w / 2, -dep / 2, w / 2, dep / 2), yaw, use_radians=True, origin=(0, 0)
            )
            fp = shapely.affinity.translate(fp, c[0], c[1])
            if (
                window.contains(fp.centroid)
                and not forbidden.intersects(fp)
                and not any(p.intersects(fp) for p in placed)
            ):
                placed.append(fp.buffer(0.5))
                rows.append(("building", c[0], c[1], w, dep, h, yaw))
                s += w + rng.uniform(*gap)
            else:
                s += 3.0
    return rows


def place_along(
    rng: np.random.Generator,
    lines: list[np.ndarray],
    kind: str,
    spacing: tuple[float, float],
    size_fn,
    *,
    normals_from=None,
    jitter: float = 0.0,
    forbidden=None,
) -> list[tuple]:
    """Structures of one kind at random spacing along polylines.

    size_fn(rng) -> (length, width, height); lamps get yaw pointing towards `normals_from`
    (the road) so their arm reaches over it.
    """
    rows = []
    for line in lines:
        ls = LineString(line)
        if ls.length < 1.0:
            continue
        s = rng.uniform(0, spacing[1])
        while s < ls.length:
            p = np.asarray(ls.interpolate(s).coords[0])
            if jitter:
                p = p + rng.normal(0, jitter, 2)
            yaw = 0.0
            if normals_from is not None:
                q = shapely.ops.nearest_points(normals_from, shapely.Point(p))[0]
                d = np.array(q.coords[0]) - p
                yaw = float(np.arctan2(d[1], d[0]))
            if forbidden is None or not forbidden.contains(shapely.Point(p)):
                size = size_fn(rng)
                rows.append((kind, p[0], p[1], size[0], size[1], size[2], yaw))
            s += rng.uniform(*spacing)
    return rows


def guardrail_segments(lines: list[np.ndarray], seg_len: float = 4.0) -> list[tuple]:
    """Guardrail as consecutive thin boxes (length seg_len, 0.3 m wide, 0.75 m tall)."""
    rows = []
    for line in lines:
        pts = resample(line, seg_len)
        for a, b in zip(pts[:-1], pts[1:]):
            d = b - a
            length = float(np.linalg.norm(d))
            if length < 0.5:
                continue
            c = (a + b) / 2
            rows.append(("guardrail", c[0], c[1], length, 0.3, 0.75, float(np.arctan2(d[1], d[0]))))
    return rows
