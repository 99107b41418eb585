from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prism3d.cli import main

PRISM3D = [sys.executable, "-m", "prism3d.cli"]


def run(args, **kw):
    return subprocess.run(PRISM3D + list(args), capture_output=True, text=True, timeout=120, **kw)


@pytest.mark.parametrize("layer", ["capture", "reconstruct", "atr", "datasets"])
def test_layer_imports_in_fresh_process(layer):
    r = subprocess.run([sys.executable, "-c", f"import prism3d.{layer} as m; print(m.__name__)"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"prism3d.{layer}"


def test_environment_set_before_heavy_imports():
    r = subprocess.run(
        [sys.executable, "-c", "import os, prism3d; print(os.environ['PYOPENGL_PLATFORM'], "
         "os.environ['NUMBA_THREADING_LAYER'], os.environ['OPENBLAS_THREAD_TIMEOUT']); import sys; "
         "print('numpy' in sys.modules)"],
        capture_output=True, text=True, timeout=60,
        env={k: v for k, v in os.environ.items()
             if k not in ("PYOPENGL_PLATFORM", "NUMBA_THREADING_LAYER", "OPENBLAS_THREAD_TIMEOUT")})
    assert r.returncode == 0, r.stderr
    line1, line2 = r.stdout.split("\n")[:2]
    assert line1 == "osmesa omp 4"  # OpenBLAS's idle threads sleep at once (numpy not loaded yet)
    assert line2 == "False"  # importing prism3d is cheap


def test_user_choice_of_egl_is_kept():
    env = dict(os.environ, PYOPENGL_PLATFORM="egl", OPENBLAS_THREAD_TIMEOUT="20")
    r = subprocess.run([sys.executable, "-c", "import os, prism3d; print(os.environ['PYOPENGL_PLATFORM'], "
                        "os.environ['OPENBLAS_THREAD_TIMEOUT'])"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.stdout.strip() == "egl 20"


def test_version_and_help_import_nothing_heavy():
    r = run(["--version"])
    assert r.returncode == 0 and r.stdout.startswith("prism3d ")
    r = run(["--help"])
    assert r.returncode == 0 and "COMMAND" in r.stdout
    # not a timing assertion on the machine: check that no heavy module is imported
    r = subprocess.run([sys.executable, "-c", "import sys; from prism3d.cli import build_parser; "
                        "build_parser(); heavy=[m for m in ('numpy','cv2','open3d','numba','pyrender') "
                        "if m in sys.modules]; print(heavy)"], capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "[]", r.stdout


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "usage" in capsys.readouterr().out


def test_unknown_command_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["frobnicate"])
    assert e.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


def test_every_command_has_help(capsys):
    from prism3d.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert "demo" in sub.choices
    for name, p in sub.choices.items():
        text = p.format_help()
        assert len(p.description or p.format_usage()) > 10, name
        assert "usage" in text


def test_prism3d_error_maps_to_exit_2(monkeypatch, capsys):
    import prism3d.demo as demo
    from prism3d.errors import InputError

    def boom(*a, **k):
        raise InputError("bad.png: something\nwrong")

    monkeypatch.setattr(demo, "run_demo", boom)
    assert main(["demo", "x"]) == 2
    err = capsys.readouterr().err
    assert err == "prism3d demo: error: bad.png: something wrong\n"


def test_max_pixels_flag_sets_the_image_budget(tmp_path, monkeypatch, capsys):
    """A 1.2 MP image is refused under --max-pixels 1000000 (from its header, nothing
    decoded or written), read under the default."""
    from prism3d.io.images import write_image

    monkeypatch.delenv("PRISM3D_MAX_PIXELS", raising=False)
    img = tmp_path / "i.png"
    write_image(img, np.zeros((1200, 1000, 3), np.uint8))
    out = tmp_path / "d.pfm"
    assert main(["--quiet", "--max-pixels", "1000000", "match", str(img), str(img), "--num-disp", "16",
                 "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "1.2 MP, more than the 1.0 MP limit (--max-pixels" in err and not out.exists()
    monkeypatch.delenv("PRISM3D_MAX_PIXELS", raising=False)
    assert main(["--quiet", "match", str(img), str(img), "--num-disp", "16", "-o", str(out)]) == 0
    with pytest.raises(SystemExit):
        main(["--max-pixels", "0", "demo", "x"])


def test_global_options_after_the_command(tmp_path, monkeypatch, capsys):
    """-q, -v and --max-pixels after the command act as before it: the same refusal, the
    same silence; one given before the command is not undone by the command's parser."""
    from prism3d.cli import build_parser
    from prism3d.io.images import write_image

    monkeypatch.delenv("PRISM3D_MAX_PIXELS", raising=False)
    img = tmp_path / "i.png"
    write_image(img, np.zeros((1200, 1000, 3), np.uint8))
    out = tmp_path / "d.pfm"
    run = ["match", str(img), str(img), "--num-disp", "16", "-o", str(out)]
    assert main([*run, "--max-pixels", "1000000", "-q"]) == 2
    assert "more than the 1.0 MP limit (--max-pixels" in capsys.readouterr().err and not out.exists()
    assert main([*run, "-q"]) == 0 and out.exists()
    assert capsys.readouterr().out == ""
    p = build_parser()
    assert p.parse_args(["-q", "-v", *run]).quiet and p.parse_args(["-q", "-v", *run]).verbose == 1
    a = p.parse_args(["db", "info", "D", "-vv", "--quiet"])
    assert a.quiet and a.verbose == 2 and a.max_pixels is None


def test_unexpected_error_keeps_traceback(monkeypatch):
    import prism3d.demo as demo

    def boom(*a, **k):
        raise ZeroDivisionError("bug")

    monkeypatch.setattr(demo, "run_demo", boom)
    with pytest.raises(ZeroDivisionError):
        main(["demo", "x"])


def test_demo_writes_report(tmp_path):
    out = tmp_path / "demo"
    r = run(["demo", str(out), "--only", "environment"])
    assert r.returncode == 0, r.stderr
    html = (out / "report.html").read_text()
    assert "<html" in html and "Installation check" in html
    assert "http://" not in html and "https://" not in html  # works offline


def test_console_script_installed():
    exe = Path(sys.executable).parent / "prism3d"
    assert exe.exists()
    r = subprocess.run([str(exe), "--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0
