"""Ground control points of a simulated flight (``simulate flight --gcp N``): painted
boards (a 2 x 2 black-and-white chequer, the usual survey marker) laid flat on open ground,
spread over the block, their true centres in the map frame and their pixels in every frame
that sees them, written as OpenDroneMap's ``gcp_list.txt``.

The file (OpenDroneMap's format): a first line naming the coordinate system (here the
site's WGS84 UTM zone, ``EPSG:326zz``; heights above the WGS84 ellipsoid, as the survey's
are), then one line per observation: ``easting northing height pixel_x pixel_y image name``.
Pixels count from the centre of the top-left pixel (OpenSfM, which ODM runs, adds half a
pixel when it reads them: the same convention as prism3d's), with Gaussian noise of
``gcp_pixel_sigma`` px per axis, as a person clicking marker centres gives.

A marker is observed in a frame only where the frame's rendered object ids show the marker
at its centre and the four pixels around it (a tree or a vehicle in front hides it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pyproj
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.capture.rig import CameraModel
from prism3d.datasets.simulation.flight_placing import Placer
from prism3d.errors import InputError
from prism3d.geo import enu_to_wgs84, utm_epsg

__all__ = ["GCP_FILE", "MARKER_THICKNESS_M", "gcp_list_text", "map_crs", "marker_mesh", "marker_side_m",
           "merged_markers", "observe_markers", "place_markers", "to_map"]

GCP_FILE = "gcp_list.txt"
#: A marker's side in ground sample distances (at least :data:`MIN_MARKER_SIDE_M`): each
#: chequer square then spans six pixels, enough to click its centre to a fraction of one.
MARKER_SIDE_GSD = 12.0
MIN_MARKER_SIDE_M = 0.6
#: Board thickness, m: the placer sinks a base 3 cm into the ground, the top stays above it.
MARKER_THICKNESS_M = 0.06
#: Frames a marker should lie in: surveyors lay control where several photographs see it
#: (a point clicked in two frames only is triangulated from one baseline). Flights where
#: too few spots are seen that often take markers seen twice.
MIN_VIEWS = 3
#: Candidate spots drawn per marker; the markers are the farthest-spread of them.
_CANDIDATES_PER_MARKER = 200
_BLACK, _WHITE, _EDGE = 0.04, 0.92, 0.5


def marker_side_m(gsd_m: float) -> float:
    """The marker's side (m) at a flight's ground sample distance, to the centimetre."""
    return max(MIN_MARKER_SIDE_M, math.ceil(100.0 * MARKER_SIDE_GSD * gsd_m) / 100.0)


def marker_mesh(side_m: float) -> SceneMesh:
    """A ``side_m`` square board (mm, centred on the origin, base at z = 0): its top a 2 x 2
    chequer (black where x y > 0), its edges grey. Each square has its own corners, so the
    colours do not blend across the centre lines."""
    h, t = 500.0 * side_m, 1000.0 * MARKER_THICKNESS_M
    verts, faces, albedo = [], [], []
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            x0, x1 = sorted((0.0, sx * h))
            y0, y1 = sorted((0.0, sy * h))
            k = len(verts)
            verts += [(x0, y0, t), (x1, y0, t), (x1, y1, t), (x0, y1, t)]
            faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
            albedo += [(_BLACK if sx * sy > 0 else _WHITE,) * 3] * 4
    k = len(verts)
    verts += [(-h, -h, 0.0), (h, -h, 0.0), (h, h, 0.0), (-h, h, 0.0),
              (-h, -h, t), (h, -h, t), (h, h, t), (-h, h, t)]
    for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):
        faces += [(k + a, k + b, k + 4 + b), (k + a, k + 4 + b, k + 4 + a)]
    albedo += [(_EDGE,) * 3] * 8
    return SceneMesh(np.array(verts), np.array(faces), np.array(albedo), None, "gcp", {"material": "lambertian"})


def _seen_by(cam: CameraModel, poses: list[NDArray], p: NDArray, margin_px: float) -> int:
    """How many of the frames ``poses`` (``T_enu_cam``) hold ENU point ``p`` inside a margin."""
    w, h = cam.size
    n = 0
    for T in poses:
        pc = (p - T[:3, 3]) @ T[:3, :3]
        if pc[2] <= 0:
            continue
        uv = cam.project(pc[None])[0]
        n += bool(np.all(uv >= margin_px) and uv[0] <= w - 1 - margin_px and uv[1] <= h - 1 - margin_px)
    return n


def place_markers(n: int, rng: np.random.Generator, placer: Placer, cam: CameraModel, poses: list[NDArray],
                  zone: tuple[float, float, float, float], side_m: float, margin_px: float
                  ) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """``n`` markers on open ground in ``zone`` (x0, x1, y0, y1, ENU m), each inside at least
    :data:`MIN_VIEWS` frames (else two), spread over the block (farthest-point choice among
    random free spots, the first the one farthest from the zone's middle). Returns per
    marker ``T_world_obj`` (mm) and its top centre (ENU m)."""
    mesh = marker_mesh(side_m)
    rad = side_m / math.sqrt(2.0)
    spots, views = [], []
    for _ in range(_CANDIDATES_PER_MARKER * n):
        x, y = rng.uniform(zone[0], zone[1]), rng.uniform(zone[2], zone[3])
        if not placer.clear(x, y, rad, 1.5):
            continue
        z = float(placer.land.height_at(np.array([x]), np.array([y]))[0])
        spots.append((x, y))
        views.append(_seen_by(cam, poses, np.array([x, y, z]), margin_px))
    v = np.array(views, dtype=np.int64)
    need = MIN_VIEWS if int((v >= MIN_VIEWS).sum()) >= n else 2
    cand = [p for p, k in zip(spots, views) if k >= need]
    if len(cand) < n:
        raise InputError(f"gcp: room for {len(cand)} ground control points seen in two frames on this flight's open "
                         f"ground, {n} asked; fly more frames or ask for fewer")
    c = np.array(cand)
    mid = np.array([(zone[0] + zone[1]) / 2.0, (zone[2] + zone[3]) / 2.0])
    chosen = [int(np.argmax(np.linalg.norm(c - mid, axis=1)))]
    dmin = np.linalg.norm(c - c[chosen[0]], axis=1)
    out = []
    while len(chosen) < n:
        k = int(np.argmax(dmin))
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(c - c[k], axis=1))
    for k in chosen:
        T = placer.put(mesh, float(c[k, 0]), float(c[k, 1]), float(rng.uniform(0.0, math.pi / 2.0)), tilt=True)
        top = T[:3, :3] @ np.array([0.0, 0.0, 1000.0 * MARKER_THICKNESS_M]) + T[:3, 3]
        out.append((T, top / 1000.0))
    return out


def merged_markers(placed: list[tuple[NDArray, NDArray]], side_m: float) -> SceneMesh:
    """All markers as one world-frame mesh (mm; a renderer of few meshes is faster)."""
    m = marker_mesh(side_m)
    V = np.vstack([m.vertices @ T[:3, :3].T + T[:3, 3] for T, _ in placed])
    F = np.vstack([m.faces + k * len(m.vertices) for k in range(len(placed))])
    A = np.vstack([m.vertex_albedo] * len(placed))
    return SceneMesh(V, F, A, None, "gcp", {"material": "lambertian", "count": len(placed)})


def observe_markers(cam: CameraModel, T_enu_cam: NDArray, centres: NDArray, ids: NDArray, marker_id: int,
                    rng: np.random.Generator, sigma_px: float) -> dict[int, tuple[list[float], list[float]]]:
    """Per marker seen in this frame: its true pixel and the clicked one (true + noise), in
    prism3d's convention. Seen: its centre projects inside the frame and the truth ids show
    the markers there and one pixel around."""
    h, w = ids.shape
    out = {}
    for g, p in enumerate(np.asarray(centres, dtype=np.float64)):
        pc = (p - T_enu_cam[:3, 3]) @ T_enu_cam[:3, :3]
        if pc[2] <= 0:
            continue
        uv = cam.project(pc[None])[0]
        c, r = int(round(uv[0])), int(round(uv[1]))
        if not (1 <= c < w - 1 and 1 <= r < h - 1):
            continue
        if not np.all(ids[[r, r - 1, r + 1, r, r], [c, c, c, c - 1, c + 1]] == marker_id):
            continue
        out[g] = ([float(uv[0]), float(uv[1])], [float(v) for v in uv + rng.normal(0.0, sigma_px, 2)])
    return out


def map_crs(origin_lla: NDArray) -> int:
    """The EPSG code the markers are written in: the site's WGS84 UTM zone."""
    return utm_epsg(float(origin_lla[0]), float(origin_lla[1]))


def to_map(enu: NDArray, origin_lla: NDArray, epsg: int) -> NDArray[np.float64]:
    """ENU m -> (easting, northing, ellipsoidal height) in ``epsg``."""
    lla = enu_to_wgs84(enu, origin_lla)
    tr = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)
    e, n = tr.transform(lla[:, 1], lla[:, 0])
    return np.stack([e, n, lla[:, 2]], axis=1)


def gcp_list_text(epsg: int, names: list[str], map_xyz: NDArray, seen: list[dict[int, Any]],
                  images: list[str]) -> str:
    """OpenDroneMap's ``gcp_list.txt``: the CRS line, then per marker, per frame that sees it,
    ``easting northing height pixel_x pixel_y image name`` (the clicked pixel)."""
    lines = [f"EPSG:{epsg}"]
    for g, name in enumerate(names):
        e, n, z = map_xyz[g]
        for k, image in enumerate(images):
            if g in seen[k]:
                x, y = seen[k][g][1]
                lines.append(f"{e:.3f} {n:.3f} {z:.3f} {x:.2f} {y:.2f} {image} {name}")
    return "\n".join(lines) + "\n"
