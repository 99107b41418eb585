"""Compile every numba kernel once, into numba's on-disk cache.

``make setup`` runs ``python -m prism3d._precompile`` once per install, so that the
first ``prism3d match``, ``prism3d reconstruct`` or ``prism3d simulate`` loads its
kernels from the cache instead of compiling them (measured on 2 shared cores: the
teddy pair's first ``prism3d match`` compiled for 28 s; the whole warm-up takes ~65 s).

A kernel is compiled once per argument-type signature (uint8 or float32 images,
uint32 or uint64 census codes, read-only or writable arrays, C or strided layout).
Listing signatures by hand would drift from the code, so each group runs the real
public functions on tiny inputs that take the same code paths as real use: the
signatures they hit are the ones real use hits. ``tests/root/test_precompile.py``
checks that a fresh process then compiles nothing.

Where the cache goes is numba's choice: ``__pycache__`` beside each kernel module
(ignored by git), or ``NUMBA_CACHE_DIR`` when set, or numba's per-user cache when
the source folder is not writable.

Each group imports what it warms up inside its own function: the groups run in separate
processes, and a process that imported every kernel module would load (and, with a cold
cache, compile) kernels it was not asked for, so these in-function imports are the point.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import prism3d  # noqa: F401  (sets NUMBA_THREADING_LAYER etc. before numba loads)

__all__ = ["GROUPS", "kernel_dispatchers", "kernel_modules", "main", "marker_path", "read_marker",
           "source_digest"]

#: Packages whose modules may hold ``@njit(cache=True)`` kernels.
KERNEL_PACKAGES = (
    "prism3d", "prism3d.capture", "prism3d.reconstruct", "prism3d.atr", "prism3d.datasets",
)
_NJIT_CACHED = re.compile(r"^[ \t]*@(?:numba\.)?njit\([^)]*cache=True", re.MULTILINE)

_MARKER = "prism3d-precompile.json"


# --- the groups -----------------------------------------------------------------------------
def _textured_pair(h: int, w: int, shift: int, seed: int = 0) -> tuple[Any, Any]:
    """An RGB uint8 pair: random blobs, the right view shifted left by ``shift`` px."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    big = rng.integers(0, 256, (h, w + shift, 3)).astype(np.uint8)
    big = cv2.GaussianBlur(big, (3, 3), 0.8)
    return np.ascontiguousarray(big[:, shift:]), np.ascontiguousarray(big[:, :w])


def _group_match() -> None:
    """Stereo matching (``prism3d match``): uint8 and float views, grey and colour,
    direct and coarse-to-fine paths, both sub-pixel methods, 4 and 8 paths, 32- and
    64-bit census codes."""
    import numpy as np

    from prism3d.reconstruct.stereo.match import MatchOptions, match_stereo_full

    left, right = _textured_pair(40, 64, 4)
    grey_l, grey_r = left[..., 0].copy(), right[..., 0].copy()
    float_l, float_r = left.astype(np.float32) / 255, right.astype(np.float32) / 255
    for lv, rv in ((left, right), (grey_l, grey_r), (float_l, float_r)):
        for c2f in (False, True):
            for sub in ("lk", "equiangular"):
                match_stereo_full(lv, rv, min_disp=0, num_disp=16,
                                  options=MatchOptions(coarse_to_fine=c2f, subpixel=sub))
    match_stereo_full(left, right, min_disp=0, num_disp=16, options=MatchOptions(paths=8))
    c77 = MatchOptions(census_window=(7, 7))
    match_stereo_full(left, right, min_disp=0, num_disp=16, options=c77)
    match_stereo_full(float_l, float_r, min_disp=0, num_disp=16, options=c77)


def _tiny_rig() -> Any:
    from prism3d.capture.rig import paper_rig

    # two 160 x 120 views at the paper's geometry (focal length scaled with the size)
    return paper_rig(sensor_size=(320, 120), focal_px=5107.0 / 10.8)


def _group_simulate() -> None:
    """The virtual rig (``prism3d simulate plate|calib|scene``): ray casting, shading,
    shadows, supersampling, sensor noise, camouflage and value-noise textures."""
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
    from prism3d.datasets.models.targets import builtin_target

    rig = _tiny_rig()
    with tempfile.TemporaryDirectory(prefix="prism3d-precompile-") as tmp:
        out = Path(tmp)
        simulate_to_folder("plate", out / "p1", SimulateOptions(supersample=1), rig=rig)
        simulate_to_folder("plate", out / "p2", SimulateOptions(supersample=2, camouflage=False, noise=False, effects=None),
                           rig=rig)
        simulate_to_folder("scene", out / "s", SimulateOptions(views=2, supersample=2), rig=rig,
                           target=builtin_target("tank_t1", seed=0))
        # a small board: the default 9 x 6 x 25 mm one does not fit the tiny views
        simulate_to_folder("calib", out / "c", SimulateOptions(views=1, supersample=1, board=(4, 3), square_mm=20.0),
                           rig=rig)


def _group_reconstruct() -> None:
    """One shot to a scan (``prism3d reconstruct``): B-spline rectification, matching,
    slanted-plane refinement, smoothing, triangulation and normals."""
    from prism3d.capture.scenes import flat_plate, place_at
    from prism3d.capture.simulate import Projector, ShotOptions, simulate_shot
    from prism3d.reconstruct.stereo.pipeline import ReconstructOptions, reconstruct_shot

    rig = _tiny_rig()
    plate = flat_plate()
    shot = simulate_shot(rig, [(plate, place_at(plate, 1250.0))], ShotOptions(supersample=1, seed=0),
                         projector=Projector.for_rig(rig, pattern=True))
    reconstruct_shot(shot.sensor_image, rig)
    reconstruct_shot(shot.sensor_image, rig, ReconstructOptions(smooth_sigma_px=1.5, refine_interpolation="linear"))


def _group_chips() -> None:
    """ATR chips (``prism3d render``, ``bank``, ``db render``): ray-cast chips."""
    from prism3d.atr.chips import ChipSpec, render_chips
    from prism3d.datasets.models.targets import builtin_target

    tank = builtin_target("tank_t1", seed=0)
    render_chips(tank, azimuth="0:360:180", chip_spec=ChipSpec(size=16, clutter="ground"))
    render_chips(tank, azimuth=0.0, chip_spec=ChipSpec(size=16))


def _group_io() -> None:
    """Point-cloud files (``stitch``, ``features`` on PCD scans): LZF decompression."""
    import struct

    import numpy as np

    from prism3d.io.pcd import read_pcd

    xyz = np.arange(12, dtype="<f4")
    n = len(xyz) // 3
    soa = b"".join(np.ascontiguousarray(xyz.reshape(n, 3)[:, k]).tobytes() for k in range(3))
    # LZF: literal runs of at most 32 bytes
    runs = [soa[i:i + 32] for i in range(0, len(soa), 32)]
    comp = b"".join(bytes([len(r) - 1]) + r for r in runs)
    header = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\n"
              f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary_compressed\n").encode()
    with tempfile.TemporaryDirectory(prefix="prism3d-precompile-") as tmp:
        p = Path(tmp) / "c.pcd"
        p.write_bytes(header + struct.pack("<II", len(comp), len(soa)) + comp)
        read_pcd(p)


def _group_grids() -> None:
    """Voxel averaging (``stitch``'s fusion and mesh, ``features``)."""
    import numpy as np

    from prism3d.grids import voxel_mean

    pts = np.random.default_rng(0).random((50, 3))
    voxel_mean(pts, 0.1, pts.astype(np.float32), None)


#: ``(name, function)`` in the order they run; each compiles (or loads) its kernels.
GROUPS: tuple[tuple[str, Callable[[], None]], ...] = (
    ("match", _group_match),
    ("reconstruct", _group_reconstruct),
    ("simulate", _group_simulate),
    ("chips", _group_chips),
    ("io", _group_io),
    ("grids", _group_grids),
)


# --- cache bookkeeping ------------------------------------------------------------------------
def kernel_modules() -> list[str]:
    """Names of the modules that define ``@njit(cache=True)`` kernels, found by reading
    the sources of :data:`KERNEL_PACKAGES` (a new kernel module needs no list)."""
    import importlib.util

    found = []
    for pkg in KERNEL_PACKAGES:
        spec = importlib.util.find_spec(pkg)
        for root in (spec.submodule_search_locations or []) if spec else []:
            for path in sorted(Path(root).rglob("*.py")):
                if "__pycache__" in path.parts:
                    continue
                if not _NJIT_CACHED.search(path.read_text(errors="replace")):
                    continue
                parts = path.relative_to(root).with_suffix("").parts
                if parts[-1] == "__init__":
                    parts = parts[:-1]
                found.append(".".join((pkg, *parts)))
    return found


def kernel_dispatchers(*, public: bool = False) -> dict[str, Any]:
    """``{"module.name": dispatcher}`` of every numba kernel in :func:`kernel_modules`
    that is compiled on its own (``inline="always"`` helpers are compiled into their
    callers and never cached alone).

    ``public``: only the kernels Python code calls. A private (``_name``) kernel is
    called from other kernels only; it is compiled with its caller, and a caller
    loaded from the cache does not load it."""
    import importlib

    from numba.core.dispatcher import Dispatcher

    out = {}
    for mod_name in kernel_modules():
        mod = importlib.import_module(mod_name)
        for name, obj in vars(mod).items():
            if (isinstance(obj, Dispatcher) and obj.py_func.__module__ == mod_name
                    and obj.targetoptions.get("inline", "never") == "never"
                    and not (public and name.startswith("_"))):
                out[f"{mod_name}.{name}"] = obj
    return out


def source_digest() -> str:
    """Hash of the kernel modules' sources, numba's version and the interpreter: the
    cache written by a warm-up serves exactly this combination."""
    import hashlib
    import importlib.util

    import numba

    h = hashlib.sha256(f"{numba.__version__} {sys.version}".encode())
    for mod_name in [*kernel_modules(), "prism3d.reconstruct.stereo._simd"]:
        spec = importlib.util.find_spec(mod_name)
        if spec is None or spec.origin is None:
            continue
        h.update(mod_name.encode())
        h.update(Path(spec.origin).read_bytes())
    return h.hexdigest()


def marker_path() -> Path:
    """Where a complete warm-up records what it covered: beside numba's cache of the
    matcher's kernels (``reconstruct/stereo/__pycache__``, or under ``NUMBA_CACHE_DIR``, or
    numba's per-user cache when the source tree is read-only)."""
    from prism3d.reconstruct.stereo import _match_kernels

    return Path(_match_kernels.census_hwc.stats.cache_path) / _MARKER


def read_marker() -> dict[str, Any] | None:
    """The last successful warm-up's record, or None."""
    try:
        return json.loads(marker_path().read_text())
    except (OSError, ValueError):
        return None


def _write_marker(record: dict[str, Any]) -> None:
    path = marker_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(record, indent=1, sort_keys=True))
        os.replace(tmp, path)
    except OSError:
        pass  # the record only serves the tests (they skip without it)


@contextlib.contextmanager
def _count_compiles() -> Iterator[dict[str, float]]:
    """``{"module.kernel(signature)": seconds}`` of the prism3d kernels numba compiles
    inside the block (numba's own helpers compiled along with them are not listed;
    a kernel compiled inside another one's compilation counts in both)."""
    from numba.core import event

    out: dict[str, float] = {}
    started: dict[int, float] = {}

    class _Listener(event.Listener):
        def on_start(self, ev: Any) -> None:
            started[id(ev.data)] = time.perf_counter()

        def on_end(self, ev: Any) -> None:
            t0 = started.pop(id(ev.data), None)
            fn = ev.data["dispatcher"].py_func
            if t0 is not None and fn.__module__.startswith("prism3d."):
                key = f"{fn.__module__}.{fn.__qualname__}{tuple(ev.data['args'])}"
                out[key] = out.get(key, 0.0) + time.perf_counter() - t0

    with event.install_listener("numba:compile", _Listener()):
        yield out


#: With two processes, a worker runs these groups (their kernels are none of the
#: matcher's) while the main process compiles the matcher; the groups after the
#: barrier use kernels of both and run once the worker is done. Two processes never
#: compile the same kernel at once: numba's cache index of a kernel is rewritten
#: whole on each save, and concurrent saves could pair a signature with another's
#: machine code.
_WORKER_GROUPS = ("simulate", "chips", "io", "grids")
_AFTER_BARRIER = ("reconstruct",)


def _run_groups(names: Sequence[str], *, quiet: bool, verbose: bool) -> tuple[list[str], int]:
    """Run the groups ``names`` in this process, in :data:`GROUPS` order; return the
    failed groups and the number of kernel signatures compiled."""
    import traceback

    failed = []
    compiled = 0
    for name, fn in GROUPS:
        if name not in names:
            continue
        t0 = time.perf_counter()
        try:
            with _count_compiles() as done:
                fn()
        except Exception:  # noqa: BLE001 - a broken group must not hide the others
            failed.append(name)
            print(f"prism3d precompile: {name}: FAILED", file=sys.stderr, flush=True)
            traceback.print_exc()
            continue
        compiled += len(done)
        if not quiet:
            print(f"prism3d precompile: {name:<12} {len(done):3d} kernels compiled "
                  f"{time.perf_counter() - t0:6.1f} s", flush=True)
            if verbose:
                for key, dt in sorted(done.items(), key=lambda kv: -kv[1]):
                    print(f"    {dt:6.2f} s  {key}", flush=True)
    return failed, compiled


def _covered() -> dict[str, list[str]]:
    """The signatures this process compiled or loaded, per public kernel."""
    return {name: sorted(str(sig) for sig in disp.signatures)
            for name, disp in kernel_dispatchers(public=True).items()}


def _default_jobs() -> int:
    """2 when a core is idle (numba compiles on one core), else 1: on a machine already
    busy a second process only competes (measured: 66 s with 1 process, 79-84 s with 2
    at a load average of 3-4 on 2 cores)."""
    cores = os.cpu_count() or 1
    try:
        idle = cores - os.getloadavg()[0]
    except OSError:
        idle = 0.0
    return 2 if cores >= 2 and idle >= 1.0 else 1


def run(groups: Sequence[str] | None = None, *, quiet: bool = False, verbose: bool = False,
        jobs: int | None = None) -> int:
    """Run the warm-up groups (all by default); return the number of groups that failed.

    ``jobs``: processes (default :func:`_default_jobs`). numba compiles on one core;
    with two processes the matcher (the longest group) compiles beside the simulator.
    """
    import logging
    import subprocess

    logging.getLogger("prism3d").setLevel(logging.ERROR)  # tiny inputs: no warnings wanted
    all_groups = [g for g, _ in GROUPS]
    wanted = all_groups if not groups else list(groups)
    unknown = sorted(set(wanted) - set(all_groups))
    if unknown:
        raise SystemExit(f"prism3d._precompile: unknown group(s): {', '.join(unknown)}")
    if jobs is None:
        jobs = _default_jobs()
    side = [g for g in wanted if g in _WORKER_GROUPS] if jobs > 1 else []
    after = [g for g in wanted if g in _AFTER_BARRIER]
    first = [g for g in wanted if g not in side and g not in after]
    t_all = time.perf_counter()
    worker = None
    with tempfile.TemporaryDirectory(prefix="prism3d-precompile-") as tmp:
        record = Path(tmp) / "worker.json"
        if side:
            cmd = [sys.executable, "-m", "prism3d._precompile", "--record", str(record), *side]
            cmd += (["-q"] if quiet else []) + (["-v"] if verbose else [])
            worker = subprocess.Popen(cmd)
        try:
            failed, compiled = _run_groups(first, quiet=quiet, verbose=verbose)
            if worker is not None:
                worker.wait()
                try:
                    rec = json.loads(record.read_text())
                except (OSError, ValueError):
                    rec = {"failed": side, "compiled": 0, "signatures": {}}
                failed += rec["failed"]
                compiled += rec["compiled"]
            f2, c2 = _run_groups(after, quiet=quiet, verbose=verbose)
        finally:
            if worker is not None and worker.poll() is None:
                worker.kill()
        failed += f2
        compiled += c2
        covered = _covered()
        if worker is not None:
            for name, sigs in rec.get("signatures", {}).items():
                covered[name] = sorted(set(covered.get(name, [])) | set(sigs))
    if not failed and set(wanted) == set(all_groups):
        _write_marker({"digest": source_digest(), "python": sys.executable,
                       "numba_cache_dir": os.environ.get("NUMBA_CACHE_DIR", ""),
                       "signatures": covered})
    if not quiet:
        procs = f"{jobs} processes" if side else "1 process"
        print(f"prism3d precompile: total {compiled} kernels compiled in "
              f"{time.perf_counter() - t_all:.1f} s ({procs})", flush=True)
    if failed:
        print(f"prism3d precompile: failed: {', '.join(failed)}", file=sys.stderr, flush=True)
    return len(failed)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m prism3d._precompile [-q] [-v] [-j N] [GROUP ...]``."""
    parser = argparse.ArgumentParser(
        prog="python -m prism3d._precompile",
        description="Compile prism3d's numba kernels into numba's on-disk cache (make setup "
        "runs this once per install; run it again after changing a kernel).")
    parser.add_argument("groups", nargs="*", metavar="GROUP",
                        help=f"groups to run (default all: {', '.join(g for g, _ in GROUPS)})")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="print nothing unless a group fails")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="also list each kernel compiled and its time")
    parser.add_argument("-j", "--jobs", type=int,
                        help="processes (default: 2 when a core is idle, else 1)")
    parser.add_argument("--record", type=Path, help=argparse.SUPPRESS)  # worker: results here
    args = parser.parse_args(argv)
    if args.record is not None:  # a worker of run(): its groups only, results to the parent
        import logging

        logging.getLogger("prism3d").setLevel(logging.ERROR)
        failed, compiled = _run_groups(args.groups, quiet=args.quiet, verbose=args.verbose)
        result = {"failed": failed, "compiled": compiled, "signatures": _covered()}
        args.record.write_text(json.dumps(result))
        return 1 if failed else 0
    return 1 if run(args.groups, quiet=args.quiet, verbose=args.verbose, jobs=args.jobs) else 0


if __name__ == "__main__":
    sys.exit(main())
