"""The numba warm-up (``python -m prism3d._precompile``, run by ``make setup``): it
covers every kernel, a fresh process after it compiles nothing, and the CLI says so
when a kernel does have to compile.

Running the warm-up itself takes minutes on a cold cache, so these tests check the
record the last warm-up left (:func:`prism3d._precompile.read_marker`) and skip when
there is none for the current kernel sources.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from prism3d import _precompile
from prism3d.progress import COMPILE_NOTICE, compile_notice


def _warm_marker() -> dict:
    marker = _precompile.read_marker()
    if marker is None:
        pytest.skip("the numba cache is not warmed up: run `python -m prism3d._precompile` "
                    "(make setup does)")
    if marker.get("digest") != _precompile.source_digest():
        pytest.skip("kernel sources (or numba) changed since the last warm-up: "
                    "run `python -m prism3d._precompile`")
    return marker


def test_kernel_modules_are_found() -> None:
    """The warm-up's record lists the kernels of every module it finds by reading the
    sources; each module found does define kernels."""
    mods = _precompile.kernel_modules()
    assert {"prism3d.reconstruct.stereo._match_kernels", "prism3d.capture._render_kernels",
            "prism3d.io._pcd_kernels"} <= set(mods)
    names = _precompile.kernel_dispatchers()
    for mod in mods:
        assert any(k.startswith(mod + ".") for k in names), mod
    public = _precompile.kernel_dispatchers(public=True)
    assert "prism3d.reconstruct.stereo._match_kernels.census_hwc" in public
    assert "prism3d.reconstruct.stereo._match_kernels._speckle_runs" not in public  # kernel-only callee


def test_warmup_covers_every_kernel() -> None:
    marker = _warm_marker()
    covered = {k for k, sigs in marker["signatures"].items() if sigs}
    missing = sorted(set(_precompile.kernel_dispatchers(public=True)) - covered)
    assert not missing, f"kernels no warm-up group runs (add a case to prism3d/_precompile.py): " \
                        f"{missing}"


_FRESH = textwrap.dedent(
    """
    import json, sys
    import prism3d  # the process environment first, as the CLI does
    import numpy as np
    from numba.core import event

    compiled = []

    class Listener(event.Listener):
        def on_start(self, ev):
            fn = ev.data["dispatcher"].py_func
            if fn.__module__.startswith("prism3d."):
                compiled.append(f"{fn.__module__}.{fn.__qualname__}{tuple(ev.data['args'])}")

        def on_end(self, ev):
            pass

    event.register("numba:compile", Listener())

    from prism3d.capture.rig import paper_rig
    from prism3d.capture.scenes import flat_plate, place_at
    from prism3d.capture.simulate import Projector, ShotOptions, simulate_shot
    from prism3d.reconstruct.stereo.match import MatchOptions, match_stereo_full
    from prism3d.reconstruct.stereo.pipeline import reconstruct_shot
    from prism3d._precompile import kernel_dispatchers

    rng = np.random.default_rng(3)
    big = rng.integers(0, 256, (30, 56, 3)).astype(np.uint8)
    left, right = big[:, 6:].copy(), big[:, :50].copy()
    match_stereo_full(left, right, min_disp=0, num_disp=16)
    match_stereo_full(left[..., 1].astype(np.float64) / 255, right[..., 1].astype(np.float64) / 255,
                      min_disp=0, num_disp=16, options=MatchOptions(coarse_to_fine=True))
    rig = paper_rig(sensor_size=(400, 150), focal_px=5107.0 / 8.64)
    plate = flat_plate()
    shot = simulate_shot(rig, [(plate, place_at(plate, 1250.0))], ShotOptions(supersample=1, seed=1),
                         projector=Projector.for_rig(rig, pattern=True))
    rec = reconstruct_shot(shot.sensor_image, rig)
    used = {k: sorted(str(s) for s in d.signatures)
            for k, d in kernel_dispatchers(public=True).items()}
    print(json.dumps({"compiled": compiled, "used": used, "points": len(rec.scan)}))
    """
)


def test_fresh_process_compiles_nothing(tmp_path) -> None:
    """After the warm-up, a new process matching and reconstructing (other sizes and
    dtypes than the warm-up's) loads every kernel from numba's cache, and uses only
    signatures the warm-up covered; the CLI prints no compile notice."""
    marker = _warm_marker()
    r = subprocess.run([sys.executable, "-c", _FRESH], check=False, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["compiled"] == [], (
        f"compiled in a fresh process after the warm-up: {out['compiled']} (a kernel numba cannot "
        "cache, or a call the warm-up misses: re-run `python -m prism3d._precompile`, then add the "
        "case to a group of prism3d/_precompile.py)")
    covered = marker["signatures"]
    extra = {k: sorted(set(s) - set(covered.get(k, []))) for k, s in out["used"].items()}
    extra = {k: v for k, v in extra.items() if v}
    assert not extra, ("signatures the warm-up does not cover (add a case to "
                       f"prism3d/_precompile.py): {extra}")

    from prism3d.io.images import write_image

    rng = np.random.default_rng(4)
    big = rng.integers(0, 256, (24, 40, 3)).astype(np.uint8)
    write_image(tmp_path / "l.png", big[:, 4:])
    write_image(tmp_path / "r.png", big[:, :36])
    r = subprocess.run([sys.executable, "-m", "prism3d.cli", "match", str(tmp_path / "l.png"),
                        str(tmp_path / "r.png"), "-o", str(tmp_path / "d.pfm"), "--num-disp", "8"],
                       check=False, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert COMPILE_NOTICE not in r.stderr


def _prism3d_function(src: str):
    """A fresh (never compiled) function that numba sees as living in a prism3d module."""
    ns: dict = {"__name__": "prism3d._notice_test"}
    exec(src, ns)  # noqa: S102 - a constant test snippet
    return ns["f"]


def test_compile_notice_once_and_quiet() -> None:
    from numba import njit

    f = njit(_prism3d_function("def f(x):\n    return x + 1\n"))
    err = io.StringIO()
    from prism3d import progress

    progress._noticed = False
    try:
        with compile_notice(quiet=True, stream=err):
            f(1)
        assert err.getvalue() == ""
        with compile_notice(stream=err):
            f(1.5)  # a new signature: compiles
            f(2.5 + 1j)  # compiles again, still one line
        assert err.getvalue() == COMPILE_NOTICE + "\n"
        g = njit(_prism3d_function("def f(x):\n    return x * 2\n"))
        progress._noticed = False
        g(1)  # outside the block: the listener is gone
        assert err.getvalue() == COMPILE_NOTICE + "\n"
    finally:
        progress._noticed = False


def test_compile_notice_hooks_a_later_numba_import() -> None:
    """Entered before numba is imported, the notice still fires (registered right after
    the import), and nothing imports numba for commands that do not need it."""
    code = textwrap.dedent(
        """
        import io, sys
        from prism3d.progress import COMPILE_NOTICE, compile_notice
        err = io.StringIO()
        with compile_notice(stream=err):
            assert "numba" not in sys.modules
        assert "numba" not in sys.modules
        with compile_notice(stream=err):
            from numba import njit
            ns = {"__name__": "prism3d._notice_test"}
            exec("def f(x):\\n    return x - 1\\n", ns)
            njit(ns["f"])(3)
        assert err.getvalue() == COMPILE_NOTICE + "\\n", err.getvalue()
        print("ok")
        """
    )
    r = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
