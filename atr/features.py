"""Size, profile, range and surface features of targets, one named column each.

:func:`model_features` (a mesh), :func:`scan_features` (a point cloud) and
:func:`view_features` (one depth view or chip) give a flat ``dict[str, float]``;
:func:`features_table` / :func:`features_to_parquet` run the first two over files.
Every column (unit in the name: ``_mm``, ``_mm2``, ``_mm3``, ``_deg``, ``_px``,
``_per_m``) is defined in docs/features.md and :data:`FEATURE_INFO`. Model and scan
features are computed with ``up`` rotated to +z and the length axis from the
footprint, so they are invariant to rotations about the vertical and translations.

References
----------
.. [1] M.-K. Hu, "Visual pattern recognition by moment invariants", IRE Trans. IT 8(2), 1962.
.. [2] C. T. Zahn, R. Z. Roskies, "Fourier descriptors for plane closed curves", IEEE TC 21(3), 1972.
.. [3] R. Osada et al., "Shape distributions", ACM TOG 21(4), 2002 (D2).
.. [4] R. B. Rusu, N. Blodow, M. Beetz, "Fast point feature histograms (FPFH)...", ICRA 2009.
.. [5] M. Pauly, M. Gross, L. P. Kobbelt, "Efficient simplification of point-sampled surfaces",
   IEEE Visualization 2002 (surface variation as a curvature estimate).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.geometry import (
    UP_AXES,
    GravityBox,
    as_camera,
    gravity_box,
    min_oriented_box,
    surface_axis,
    up_rotation,
)
from prism3d.capture.rig import CameraModel
from prism3d.checks import check_array, check_choice, check_same_shape
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path
from prism3d.io.mesh import UNITS_MM, read_mesh
from prism3d.io.pcd import read_pcd
from prism3d.io.ply import read_ply
from prism3d.io.units import FORWARD_AXES, declared_units
from prism3d.reconstruct.scan.surface import surface_extents, surface_points

__all__ = [
    "FEATURES_SCHEMA_VERSION",
    "FEATURE_INFO",
    "UNITS_MM",
    "features_table",
    "features_to_parquet",
    "model_features",
    "read_units_sidecar",
    "scan_features",
    "view_features",
]

#: Version of the feature table layout (column names and definitions).
FEATURES_SCHEMA_VERSION = 1

N_SAMPLES = 4096  # surface samples for profile / surface features (fixed seed)
N_STATIONS = 10  # profile stations along the length axis
N_ELEV_BINS = 6  # normal elevation histogram, 15 deg bins
N_D2_BINS = 10
N_D2_PAIRS = 8192
N_RANGE_BINS = 8
N_FOURIER = 8
N_FPFH = 33
_SEED = 0
N_CURV_NEIGHBOURS = 16  # surface variation from 16 neighbours: smooth yet local on 4096 samples
FPFH_RADIUS = 0.1  # FPFH support radius, fraction of the box diagonal
FPFH_MAX_NN = 64  # neighbours per FPFH support (bounds the cost on dense samples)
N_NORMAL_NEIGHBOURS = 20  # Open3D normal estimation for scans without normals
N_OUTLINE = 64  # outline resampled to 64 points for the Fourier descriptors
MIN_POINTS = 10  # fewer points (or supported surface vertices) give no meaningful box

ProgressFn = Callable[[int, int, str], None]


# -- machine-readable description ---------------------------------------------------------
def _build_info() -> dict[str, dict[str, Any]]:
    """``name -> {unit, source, invariant_to, definition}`` (terms: docs/features.md)."""
    info: dict[str, dict[str, Any]] = {}
    MS = ("model", "scan")
    RIG = ["translation", "rotation_about_vertical"]
    RIGS = RIG + ["scale"]

    def add(name: str, unit: str, src: Sequence[str], inv: list[str], text: str) -> None:
        info[name] = {"unit": unit, "source": list(src), "invariant_to": list(inv), "definition": text}

    add("length_mm", "mm", MS, RIG, "longer horizontal side of the gravity-aligned box, oriented by the horizontal principal axes of the surface (minimum-area footprint rectangle when isotropic)")
    add("width_mm", "mm", MS, RIG, "shorter horizontal side of the gravity-aligned box")
    add("height_mm", "mm", MS, RIG, "vertical extent (along the up axis)")
    add("obb_major_mm", "mm", MS, RIG + ["any_rotation"], "longest side of the minimum-volume oriented box (no gravity constraint)")
    add("obb_middle_mm", "mm", MS, RIG + ["any_rotation"], "middle side of the minimum-volume oriented box")
    add("obb_minor_mm", "mm", MS, RIG + ["any_rotation"], "shortest side of the minimum-volume oriented box")
    add("length_width_ratio", "1", MS, RIGS, "length_mm / width_mm")
    add("length_height_ratio", "1", MS, RIGS, "length_mm / height_mm")
    add("volume_mm3", "mm3", MS, RIG + ["any_rotation"], "enclosed mesh volume when the mesh is watertight, else the convex hull volume (see volume_is_hull); scans: convex hull volume")
    add("volume_is_hull", "1", MS, RIGS, "1 when volume_mm3 is the convex hull volume, 0 when it is the mesh's own volume")
    add("hull_volume_mm3", "mm3", MS, RIG + ["any_rotation"], "convex hull volume")
    add("surface_area_mm2", "mm2", ("model",), RIG + ["any_rotation"], "sum of triangle areas (NaN for scans)")
    add("box_fill_ratio", "1", MS, RIGS, "volume_mm3 / (length_mm * width_mm * height_mm)")
    for i in range(N_STATIONS):
        pct = round(100 * (i + 0.5) / N_STATIONS)
        add(f"height_profile_{pct:02d}", "1", MS, RIGS,
            f"top height (above the lowest point) of the surface in the length station centred at {pct}% of the length, divided by height_mm")
        add(f"width_profile_{pct:02d}", "1", MS, RIGS,
            f"width of the surface in the length station centred at {pct}% of the length, divided by width_mm")
    add("curvature_mean", "1", MS, RIGS, "mean surface variation l0/(l0+l1+l2) of the 16-nearest-neighbour covariance of the surface samples")
    add("curvature_std", "1", MS, RIGS, "standard deviation of the surface variation")
    add("curvature_p90", "1", MS, RIGS, "90th percentile of the surface variation")
    for i in range(N_ELEV_BINS):
        lo, hi = 90 // N_ELEV_BINS * i, 90 // N_ELEV_BINS * (i + 1)
        add(f"normal_elev_{lo:02d}_{hi:02d}_frac", "1", MS, RIGS,
            f"area fraction of surface whose normal makes {lo}-{hi} deg with the horizontal plane (unsigned; soft binning, linear between bin centres)")
    for i in range(N_D2_BINS):
        add(f"d2_hist_{i:02d}", "1", MS, RIGS + ["any_rotation"],
            f"D2 shape distribution: fraction of {N_D2_PAIRS} random surface point pairs (fixed seed) whose distance / box diagonal is in [{i / N_D2_BINS:.1f}, {(i + 1) / N_D2_BINS:.1f})")
    add("d2_mean_ratio", "1", MS, RIGS + ["any_rotation"], "mean D2 pair distance / box diagonal")
    for i in range(N_FPFH):
        add(f"fpfh_{i:02d}", "1", MS, RIGS + ["any_rotation"],
            f"bin {i} of the mean FPFH (Open3D, radius 10% of the box diagonal) over the surface samples")
    add("n_points", "1", MS, RIG + ["any_rotation"], "vertices (model) or points (scan) in the input")
    _add_view_info(add)
    return info


def _add_view_info(add: Callable[[str, str, Sequence[str], list[str], str], None]) -> None:
    """The view columns of :data:`FEATURE_INFO` (one depth view), in order, through
    :func:`_build_info`'s ``add(name, unit, source, invariant_to, definition)``."""
    VS = ("view",)
    add("range_mm", "mm", VS, ["image_rotation"], "median depth of the target pixels")
    add("range_min_mm", "mm", VS, ["image_rotation"], "nearest target depth")
    add("range_max_mm", "mm", VS, ["image_rotation"], "farthest target depth")
    add("range_extent_mm", "mm", VS, ["image_rotation"], "range_max_mm - range_min_mm")
    for i in range(N_RANGE_BINS):
        add(f"range_hist_{i:02d}", "1", VS, ["image_rotation", "scale_approx"],
            f"fraction of target pixels whose (depth - range_min) / range_extent is in bin {i} of {N_RANGE_BINS}")
    add("pixels_on_target_px", "px", VS, ["image_rotation"], "number of target pixels")
    add("pixels_per_m", "px/m", VS, ["image_rotation"], "pixels per metre at the target range: fx * 1000 / range_mm")
    add("silhouette_area_mm2", "mm2", VS, ["image_rotation", "range"], "sum over target pixels of the pixel footprint (z/fx)(z/fy) at its depth")
    add("silhouette_width_mm", "mm", VS, ["range"], "horizontal image extent of the target times range_mm / fx")
    add("silhouette_height_mm", "mm", VS, ["range"], "vertical image extent of the target times range_mm / fy")
    add("relief_rms_mm", "mm", VS, ["image_rotation", "range"], "RMS of the target depth about its least-squares plane")
    for i in range(7):
        add(f"hu_{i + 1}", "1", VS, ["image_rotation", "scale" if i < 6 else "scale_approx", "translation"],
            f"Hu moment invariant {i + 1} of the silhouette, as -sign(h) log10|h| (hu_7 changes sign under mirroring)")
    add("elongation", "1", VS, ["image_rotation", "scale", "translation"], "1 - sqrt(minor / major eigenvalue) of the silhouette's second moments")
    add("compactness", "1", VS, ["image_rotation", "translation"], "4 pi area / perimeter^2 of the largest outline (1 = disc; pixel perimeter makes it mildly scale dependent)")
    add("solidity", "1", VS, ["image_rotation", "scale_approx", "translation"], "silhouette area / convex hull area of the largest outline")
    for k in range(N_FOURIER):
        add(f"fourier_{k + 2:02d}", "1", VS, ["image_rotation", "scale_approx", "translation"],
            f"Fourier descriptor: (|C_{k + 2}| + |C_-{k + 2}|) / (|C_1| + |C_-1|) of the largest outline resampled to 64 points by arc length (start point invariant)")


#: Machine-readable description of every feature column (see :func:`_build_info`).
FEATURE_INFO: dict[str, dict[str, Any]] = _build_info()


# -- helpers ------------------------------------------------------------------------------
def _check_mesh(vertices: NDArray, faces: NDArray) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    V = check_array(vertices, "vertices", ndim=2, dtype_kind="fiu")
    F = check_array(faces, "faces", ndim=2, dtype_kind="iu")
    if V.shape[0] == 0 or F.shape[0] == 0:
        raise InputError(f"empty mesh: {V.shape[0]} vertices, {F.shape[0]} faces; need at least one triangle")
    if V.shape[1] != 3:
        raise InputError(f"vertices: expected shape (N, 3), got {V.shape}")
    if F.shape[1] != 3:
        raise InputError(f"faces: expected shape (M, 3) triangles, got {F.shape}")
    if not np.all(np.isfinite(V)):
        raise InputError("vertices: expected finite values, found NaN or inf")
    if F.min() < 0 or F.max() >= V.shape[0]:
        raise InputError(f"faces: vertex indices must be in [0, {V.shape[0] - 1}], got [{F.min()}, {F.max()}]")
    return V.astype(np.float64), F.astype(np.int64)


def _sample_surface(V: NDArray, F: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """Area-weighted uniform surface samples (fixed seed) and their face normals."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cr = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cr, axis=1)
    ok = area2 > 0
    if not np.any(ok):
        raise InputError("mesh: every triangle is degenerate (zero area)")
    rng = np.random.default_rng(_SEED)
    p = area2 / area2.sum()
    fi = rng.choice(len(F), size=n, p=p)
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    pts = (1 - r1)[:, None] * a[fi] + (r1 * (1 - r2))[:, None] * b[fi] + (r1 * r2)[:, None] * c[fi]
    nrm = cr[fi] / area2[fi, None]
    return pts, nrm


def _canonical_coords(P: NDArray, box: Any) -> NDArray:
    """Points in the gravity box frame (length, width, up) with the length axis sign
    fixed by positive skewness of the points along it."""
    q = (P - box.center) @ box.axes.T
    l = q[:, 0]
    m3 = np.mean((l - l.mean()) ** 3)
    if m3 < 0:
        q[:, 0] = -q[:, 0]
        q[:, 1] = -q[:, 1]
    return q


def _profiles(q: NDArray, L: float, W: float, H: float) -> dict[str, float]:
    out: dict[str, float] = {}
    zmin = q[:, 2].min()
    edges = np.linspace(-L / 2, L / 2, N_STATIONS + 1)
    idx = np.clip(np.searchsorted(edges, q[:, 0], side="right") - 1, 0, N_STATIONS - 1)
    for i in range(N_STATIONS):
        pct = round(100 * (i + 0.5) / N_STATIONS)
        sel = idx == i
        if np.any(sel) and H > 0 and W > 0:
            hp = (q[sel, 2].max() - zmin) / H
            wp = (q[sel, 1].max() - q[sel, 1].min()) / W
        else:
            hp = wp = 0.0
        out[f"height_profile_{pct:02d}"] = float(hp)
        out[f"width_profile_{pct:02d}"] = float(wp)
    return out


def _curvature(P: NDArray) -> dict[str, float]:
    from scipy.spatial import cKDTree

    k = min(N_CURV_NEIGHBOURS, len(P))
    _, nb = cKDTree(P).query(P, k=k)
    X = P[nb] - P[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", X, X) / k
    ev = np.linalg.eigvalsh(cov)
    tot = ev.sum(axis=1)
    sv = np.where(tot > 0, ev[:, 0] / np.where(tot > 0, tot, 1.0), 0.0)
    return {
        "curvature_mean": float(sv.mean()),
        "curvature_std": float(sv.std()),
        "curvature_p90": float(np.percentile(sv, 90)),
    }


def _elev_hist(N: NDArray) -> dict[str, float]:
    n = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    elev = np.degrees(np.arcsin(np.clip(np.abs(n[:, 2]), 0.0, 1.0)))
    step = 90 // N_ELEV_BINS
    # soft binning (linear between bin centres): no jumps for facets at bin edges
    x = np.clip(elev / step - 0.5, 0.0, N_ELEV_BINS - 1.0)
    i0 = np.floor(x).astype(np.int64)
    i1 = np.minimum(i0 + 1, N_ELEV_BINS - 1)
    fr = x - i0
    hist = np.bincount(i0, 1 - fr, N_ELEV_BINS) + np.bincount(i1, fr, N_ELEV_BINS)
    hist = hist / max(len(elev), 1)
    return {f"normal_elev_{step * i:02d}_{step * (i + 1):02d}_frac": float(h) for i, h in enumerate(hist)}


def _d2(P: NDArray, diag: float) -> dict[str, float]:
    rng = np.random.default_rng(_SEED + 1)
    i = rng.integers(len(P), size=N_D2_PAIRS)
    j = rng.integers(len(P), size=N_D2_PAIRS)
    d = np.linalg.norm(P[i] - P[j], axis=1) / max(diag, 1e-12)
    hist, _ = np.histogram(np.clip(d, 0, 1 - 1e-12), bins=np.linspace(0, 1, N_D2_BINS + 1))
    out = {f"d2_hist_{k:02d}": float(h / N_D2_PAIRS) for k, h in enumerate(hist)}
    out["d2_mean_ratio"] = float(d.mean())
    return out


def _fpfh(P: NDArray, N: NDArray, diag: float) -> dict[str, float]:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(P, dtype=np.float64)))
    pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(N, dtype=np.float64))
    f = o3d.pipelines.registration.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS * diag, max_nn=FPFH_MAX_NN)
    )
    m = np.asarray(f.data).mean(axis=1)
    return {f"fpfh_{i:02d}": float(v) for i, v in enumerate(m)}


def _hull_volume(P: NDArray) -> float:
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(P).volume)
    except (QhullError, ValueError):
        return 0.0


def _common(P_all: NDArray, S: NDArray, SN: NDArray, axis: NDArray | None = None, *,
            measured: bool = False) -> tuple[dict[str, float], Any]:
    """Box, OBB, profiles and surface features from all points ``P_all`` (z up; the
    boxes enclose them) and surface samples ``S`` with normals ``SN``. ``measured``: the
    box's sides read from a scan's surface (:func:`surface_extents`, as the object frame's)."""
    box = gravity_box(P_all, axis_points=S, axis=axis)
    if measured:
        lo, hi = surface_extents(P_all, box.axes)
        box = GravityBox(float(hi[0] - lo[0]), float(hi[1] - lo[1]), float(hi[2] - lo[2]), box.axes,
                         box.axes.T @ ((lo + hi) / 2))
    L, W, H = box.length_mm, box.width_mm, box.height_mm
    ext, _ = min_oriented_box(P_all)
    diag = float(np.sqrt(L * L + W * W + H * H))
    out: dict[str, float] = {
        "length_mm": L,
        "width_mm": W,
        "height_mm": H,
        "obb_major_mm": float(ext[0]),
        "obb_middle_mm": float(ext[1]),
        "obb_minor_mm": float(ext[2]),
        "length_width_ratio": L / W if W > 0 else math.nan,
        "length_height_ratio": L / H if H > 0 else math.nan,
    }
    out.update(_profiles(_canonical_coords(S, box), L, W, H))
    out.update(_curvature(S))
    out.update(_elev_hist(SN))
    out.update(_d2(S, diag))
    out.update(_fpfh(S, SN, diag))
    return out, box


def _order(d: dict[str, float], source: str) -> dict[str, float]:
    """Columns in FEATURE_INFO order for ``source``; NaN for those that do not apply."""
    names = [k for k, v in FEATURE_INFO.items() if set(v["source"]) & {"model", "scan"}] if source != "view" \
        else [k for k, v in FEATURE_INFO.items() if "view" in v["source"]]
    return {k: float(d.get(k, math.nan)) for k in names}


# -- public API ---------------------------------------------------------------------------
def model_features(vertices: NDArray, faces: NDArray, *, up: str = "z") -> dict[str, float]:
    """Features of a triangle mesh: ``vertices`` (N, 3) mm, ``faces`` (M, 3) int, ``up`` the
    axis pointing up ("z", "y", "x", "-z", ...).

    Returns every model/scan column of :data:`FEATURE_INFO`, in order; the volume is the
    mesh's own when watertight, else the hull's (``volume_is_hull`` = 1). Raises
    InputError on an empty mesh, bad shapes or indices, non-finite vertices, bad ``up``.
    """
    import trimesh

    V, F = _check_mesh(vertices, faces)
    check_choice(up, "up", UP_AXES)
    V = V @ up_rotation(up).T
    S, SN = _sample_surface(V, F, N_SAMPLES)
    out, _ = _common(V, S, SN, surface_axis(V, F))
    mesh = trimesh.Trimesh(V, F, process=False)
    hull_v = _hull_volume(V)
    if mesh.is_watertight:
        vol, is_hull = abs(float(mesh.volume)), 0.0
    else:
        vol, is_hull = hull_v, 1.0
    out.update(
        volume_mm3=vol,
        volume_is_hull=is_hull,
        hull_volume_mm3=hull_v,
        surface_area_mm2=float(mesh.area),
        n_points=float(len(V)),
    )
    bv = out["length_mm"] * out["width_mm"] * out["height_mm"]
    out["box_fill_ratio"] = vol / bv if bv > 0 else math.nan
    return _order(out, "model")


def scan_features(points: NDArray, normals: NDArray | None = None, *, up: str = "z",
                  box: str = "auto") -> dict[str, float]:
    """Features of a point cloud (a scan) in millimetres.

    ``points`` (N, 3) mm, NaN rows dropped, >= 10 finite; ``normals`` (N, 3) (sign
    irrelevant; estimated from 20 neighbours when absent); ``up`` as for
    :func:`model_features`. ``box``: what the boxes enclose: "points" (every point),
    "surface" (the points near their fitted surface, sides read as the object frame's:
    :mod:`prism3d.reconstruct.scan.surface`; needs outward normals) or "auto" (surface when
    normals are given and the cloud spans >= ``DENSE_SPACINGS`` spacings; why:
    docs/features.md). Raises InputError on bad shapes, < 10 points, bad ``up``.
    """
    P = check_array(points, "points", ndim=2, dtype_kind="fiu")
    if P.shape[1] != 3:
        raise InputError(f"points: expected shape (N, 3), got {P.shape}")
    check_choice(up, "up", UP_AXES)
    check_choice(box, "box", ("auto", "surface", "points"))
    if box == "surface" and normals is None:
        raise InputError("box='surface' needs the points' outward normals")
    ok = np.all(np.isfinite(P), axis=1)
    if normals is not None:
        Nn = check_array(normals, "normals", shape=(P.shape[0], 3), dtype_kind="f")
        ok &= np.all(np.isfinite(Nn), axis=1)
    if ok.sum() < MIN_POINTS:
        raise InputError(f"points: need at least {MIN_POINTS} finite points, got {int(ok.sum())}")
    R = up_rotation(up)
    P = P[ok].astype(np.float64) @ R.T
    if normals is not None:
        N = Nn[ok].astype(np.float64) @ R.T
    else:
        import open3d as o3d

        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(N_NORMAL_NEIGHBOURS))
        N = np.asarray(pc.normals)
    if len(P) > N_SAMPLES:
        sel = np.sort(np.random.default_rng(_SEED).choice(len(P), N_SAMPLES, replace=False))
    else:
        sel = np.arange(len(P))
    # "surface" without normals was refused above; "auto" sorts dense clouds given normals
    surface = box == "surface" or (box == "auto" and normals is not None)
    P_box, measured = surface_points(P, N, sparse=box == "surface") if surface else (P, False)
    out, _ = _common(P_box, P[sel], N[sel], measured=measured)
    hull_v = _hull_volume(P)
    out.update(volume_mm3=hull_v, volume_is_hull=1.0, hull_volume_mm3=hull_v,
               surface_area_mm2=math.nan, n_points=float(len(P)))
    bv = out["length_mm"] * out["width_mm"] * out["height_mm"]
    out["box_fill_ratio"] = hull_v / bv if bv > 0 else math.nan
    return _order(out, "scan")


def view_features(depth_mm: NDArray, mask: NDArray | None, K: NDArray | CameraModel) -> dict[str, float]:
    """Range and silhouette features of one depth view (e.g. a 128x128 chip).

    ``depth_mm`` (H, W) mm along z, NaN = no surface; ``mask`` (H, W) bool target pixels
    or None (every finite depth); ``K`` (3, 3) or CameraModel (fx, fy only). Returns the
    view columns of :data:`FEATURE_INFO` in order; InputError if no target pixel.
    """
    import cv2

    d = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="fiu")
    h, w = d.shape
    cam = as_camera(K, (w, h))
    m = np.isfinite(d) & (d > 0)
    if mask is not None:
        mk = check_array(mask, "mask", ndim=2)
        check_same_shape(mk, d, ("mask", "depth_mm"))
        m &= mk.astype(bool)
    n = int(m.sum())
    if n == 0:
        raise InputError("depth_mm/mask: no target pixel with a finite depth (all NaN or empty mask)")
    z = d[m].astype(np.float64)
    out = _range_features(z)
    rng_mm = out["range_mm"]
    vv, uu = np.nonzero(m)
    out["pixels_on_target_px"] = float(n)
    out["pixels_per_m"] = cam.fx * 1000.0 / rng_mm
    out["silhouette_area_mm2"] = float(np.sum(z * z) / (cam.fx * cam.fy))
    out["silhouette_width_mm"] = float((uu.max() - uu.min() + 1) * rng_mm / cam.fx)
    out["silhouette_height_mm"] = float((vv.max() - vv.min() + 1) * rng_mm / cam.fy)
    out["relief_rms_mm"] = _relief_rms(uu, vv, z)
    m8 = m.astype(np.uint8)
    mo = cv2.moments(m8, binaryImage=True)
    hu = cv2.HuMoments(mo).ravel()
    with np.errstate(divide="ignore"):
        safe = np.where(hu != 0, np.abs(hu), 1.0)  # log10 only of non-zero moments
        hu_log = np.where(hu != 0, -np.sign(hu) * np.log10(safe), 0.0)
    out.update({f"hu_{i + 1}": float(v) for i, v in enumerate(hu_log)})
    mu20, mu02, mu11 = mo["mu20"], mo["mu02"], mo["mu11"]
    tr = mu20 + mu02
    disc = math.sqrt(max((mu20 - mu02) ** 2 + 4 * mu11 * mu11, 0.0))
    lmax, lmin = (tr + disc) / 2, (tr - disc) / 2
    out["elongation"] = float(1 - math.sqrt(max(lmin, 0.0) / lmax)) if lmax > 0 else 0.0
    contours, _ = cv2.findContours(m8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    per = cv2.arcLength(c.astype(np.float32).reshape(-1, 1, 2), True)
    area_c = cv2.contourArea(c.astype(np.float32))
    out["compactness"] = float(4 * math.pi * area_c / per**2) if per > 0 else 0.0
    hull_a = cv2.contourArea(cv2.convexHull(c.astype(np.float32)))
    out["solidity"] = float(area_c / hull_a) if hull_a > 0 else 1.0
    out.update(_fourier(c))
    return _order(out, "view")


def _range_features(z: NDArray[np.float64]) -> dict[str, float]:
    """Range columns of a view from its target pixels' depths ``z`` (mm): median, nearest,
    farthest, extent and the histogram of depths over that extent."""
    n = len(z)
    zmin, zmax = float(z.min()), float(z.max())
    rng_mm = float(np.median(z))
    ext = zmax - zmin
    out: dict[str, float] = {
        "range_mm": rng_mm, "range_min_mm": zmin, "range_max_mm": zmax, "range_extent_mm": ext,
    }
    rel = (z - zmin) / ext if ext > 0 else np.zeros_like(z)
    hist = np.bincount(np.minimum((rel * N_RANGE_BINS).astype(np.int64), N_RANGE_BINS - 1),
                       minlength=N_RANGE_BINS) / n
    out.update({f"range_hist_{i:02d}": float(v) for i, v in enumerate(hist)})
    return out


def _relief_rms(uu: NDArray, vv: NDArray, z: NDArray[np.float64]) -> float:
    """RMS (mm) of the depths ``z`` at pixels ``(vv, uu)`` about their least-squares plane;
    0 for fewer than 3 pixels."""
    n = len(z)
    if n >= 3:
        A = np.column_stack([uu, vv, np.ones(n)]).astype(np.float64)
        coef, *_ = np.linalg.lstsq(A, z, rcond=None)
        return float(np.sqrt(np.mean((z - A @ coef) ** 2)))
    return 0.0


def _fourier(c: NDArray) -> dict[str, float]:
    """Rotation / scale / start-point invariant Fourier descriptors of a closed outline."""
    if len(c) < 3:
        return {f"fourier_{k + 2:02d}": 0.0 for k in range(N_FOURIER)}
    closed = np.vstack([c, c[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], N_OUTLINE, endpoint=False)
    x = np.interp(t, s, closed[:, 0])
    y = np.interp(t, s, closed[:, 1])
    C = np.abs(np.fft.fft(x + 1j * y))
    base = C[1] + C[-1]
    out = {}
    for k in range(N_FOURIER):
        f = k + 2
        out[f"fourier_{f:02d}"] = float((C[f] + C[-f]) / base) if base > 0 else 0.0
    return out


# -- files --------------------------------------------------------------------------------
_MESH_EXT = {".obj", ".glb", ".gltf", ".off", ".stl"}
_SCAN_EXT = {".pcd", ".xyz", ".pts"}


def read_units_sidecar(path: str | Path) -> dict[str, str] | None:
    """``<file>.units.yaml`` beside ``path`` (keys ``units``: mm cm m in, ``up``: x y z -x
    -y -z, ``forward``: the nose's axis, x y z -x -y -z; anything else is an error), or
    None when there is none."""
    import yaml

    side = Path(str(path) + ".units.yaml")
    if not side.is_file():
        return None
    try:
        data = yaml.safe_load(side.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(f"{side}: invalid YAML ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(f"{side}: expected a mapping with keys units, up")
    unknown = set(data) - {"units", "up", "forward"}
    if unknown:
        raise InputError(f"{side}: unknown keys {sorted(unknown)}; allowed: units, up, forward")
    out = {k: str(v) for k, v in data.items()}
    if "units" in out:
        check_choice(out["units"], f"{side}: units", list(UNITS_MM))
    if "up" in out:
        check_choice(out["up"], f"{side}: up", UP_AXES)
    if "forward" in out:
        check_choice(out["forward"], f"{side}: forward", FORWARD_AXES)
    return out


def _load(path: Path) -> tuple[str, NDArray, NDArray | None, NDArray | None, str | None]:
    """``(kind, points_or_vertices, faces, normals, units_in_file)``."""
    ext = path.suffix.lower()
    if ext == ".ply":
        ply = read_ply(path)
        units, _ = declared_units(ply.comments)
        if ply.faces is not None and len(ply.faces):
            return "mesh", ply.points, ply.faces, None, units
        return "scan", ply.points, None, ply.normals, units
    if ext in _MESH_EXT:
        mesh = read_mesh(path)
        return "mesh", mesh.vertices, mesh.faces, None, None
    if ext == ".pcd":
        pc = read_pcd(path)
        if len(pc.points) == 0:
            raise InputError(f"{path}: empty point cloud")
        return "scan", pc.points, None, pc.normals, None
    raise InputError(
        f"{path}: unsupported format {ext!r} (meshes: .obj .glb .gltf .off .stl .ply; scans: .ply .pcd)"
    )


def _resolve(path: Path, file_units: str | None, units: str | None, up: str | None) -> tuple[str, str]:
    side = read_units_sidecar(path) or {}
    known = side.get("units", file_units)
    if file_units is not None and "units" in side and side["units"] != file_units:
        raise InputError(f"{path}: the file says units {file_units} but its sidecar says {side['units']}")
    if units is not None:
        check_choice(units, "units", list(UNITS_MM))
    if known is not None:
        check_choice(known, f"{path}: units", list(UNITS_MM))
        if units is not None and units != known:
            raise InputError(
                f"{path}: declares units {known!r} (file or .units.yaml sidecar) but --units {units} was given; "
                f"remove --units or fix the declaration"
            )
        u = known
    elif units is not None:
        u = units
    else:
        raise InputError(
            f"{path}: no units known for this file: pass --units (mm, cm, m, in) or write a sidecar "
            f"{path.name}.units.yaml with 'units: ...' and 'up: ...'"
        )
    up_v = side.get("up", up)
    if "up" in side and up is not None and up != side["up"]:
        raise InputError(f"{path}: its .units.yaml sidecar says up {side['up']!r} but --up {up} was given")
    if up_v is None:
        raise InputError(f"{path}: no up axis known: pass --up (y or z) or set 'up:' in {path.name}.units.yaml")
    check_choice(up_v, "up", UP_AXES)
    return u, up_v


def features_table(
    paths: Sequence[str | Path],
    *,
    units: str | None = None,
    up: str | None = None,
    box: str = "auto",
    progress: ProgressFn | None = None,
) -> Any:
    """One row of features per model or scan file (pandas DataFrame).

    ``paths``: meshes (.obj .glb .gltf .off .stl, .ply with faces) and scans (.ply, .pcd).
    ``units`` (mm cm m in) for files that do not declare theirs (PLY comment ``units``
    or a ``.units.yaml`` sidecar; a contradiction is an error, never guessed); ``up``
    unless the sidecar gives it; ``box`` as for :func:`scan_features`; ``progress``
    ``(done, total, label)``. Columns ``source kind units_in up_in schema_version`` then
    every model/scan feature, in mm.
    """
    import pandas as pd

    if isinstance(paths, (str, Path)):
        paths = [paths]
    if len(paths) == 0:
        raise InputError("features: no input files given")
    check_choice(box, "box", ("auto", "surface", "points"))
    rows = []
    total = len(paths)
    for i, p in enumerate(paths):
        path = Path(p)
        if not path.is_file():
            raise InputError(f"{path}: file not found")
        if progress is not None:
            progress(i, total, path.name)
        kind, pts, faces, normals, file_units = _load(path)
        u, up_v = _resolve(path, file_units, units, up)
        pts = np.asarray(pts, dtype=np.float64) * UNITS_MM[u]
        try:
            feats = model_features(pts, faces, up=up_v) if kind == "mesh" else scan_features(pts, normals, up=up_v, box=box)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from exc
        rows.append({"source": str(path), "kind": kind, "units_in": u, "up_in": up_v,
                     "schema_version": FEATURES_SCHEMA_VERSION, **feats})
    if progress is not None:
        progress(total, total, "done")
    return pd.DataFrame(rows)


def features_to_parquet(
    paths: Sequence[str | Path],
    out_path: str | Path,
    *,
    units: str | None = None,
    up: str | None = None,
    box: str = "auto",
    progress: ProgressFn | None = None,
) -> Any:
    """``prism3d features MODEL_OR_SCAN... -o features.parquet [--units U] [--up y|z] [--box B]``:
    :func:`features_table` written atomically as Parquet, with key-value metadata
    ``prism3d_features_schema_version`` and ``prism3d_feature_units`` (JSON column ->
    unit). Returns the DataFrame.
    """
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    if Path(out_path).suffix.lower() != ".parquet":
        raise InputError(f"{out_path}: the features are written as Parquet; name the file .parquet")
    if Path(out_path).is_dir():
        raise InputError(f"{out_path}: is a folder; give an output file name")
    df = features_table(paths, units=units, up=up, box=box, progress=progress)
    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"prism3d_features_schema_version"] = str(FEATURES_SCHEMA_VERSION).encode()
    meta[b"prism3d_feature_units"] = json.dumps(
        {k: v["unit"] for k, v in FEATURE_INFO.items() if k in df.columns}
    ).encode()
    table = table.replace_schema_metadata(meta)
    with atomic_path(out_path) as tmp:
        pq.write_table(table, str(tmp))
    return df
