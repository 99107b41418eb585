"""Atomic file output: a temp file in the same folder, then ``os.replace``.

An interrupted run leaves either the old file or the new one, never half of one.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from prism3d.errors import InputError, Prism3dError

__all__ = ["check_outputs", "atomic_path", "atomic_paths", "atomic_open", "atomic_write_bytes", "atomic_write_text", "output_lock", "staged_folder"]


@contextlib.contextmanager
def atomic_path(path: str | Path, *, keep_suffix: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success move it onto ``path``.

    The temp name keeps the target's suffix so libraries that choose a format by
    extension (OpenCV, Open3D) still work; ``keep_suffix=False`` where a reader of the
    folder globs by suffix (``*.parquet``) and must never see a half-written file. On
    any exception the temp file is removed and ``path`` is untouched.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}" if keep_suffix else ".tmp", dir=target.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; keep the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        renamed = _renamed(exc, str(tmp_path), str(target))  # e.g. disk full: name the output
        if renamed is exc:
            raise
        raise renamed from exc
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def check_outputs(files: list[str | Path] | tuple = (), folders: list[str | Path] | tuple = ()) -> None:
    """Before any work: each output file is not a folder, each output folder not a file,
    no two outputs name one path, and a file can be created where each will go (a
    throw-away temp file in its nearest existing folder: permissions, read-only and
    pseudo file systems, a file where a folder should be). InputError names the output."""
    outs = [(Path(p), False) for p in files] + [(Path(p), True) for p in folders]
    seen: dict[Path, Path] = {}
    for p, is_folder in outs:
        r = p.resolve()
        if r in seen:
            raise InputError(f"{p}: named twice as an output (also {seen[r]})")
        seen[r] = p
        if not is_folder and p.is_dir():
            raise InputError(f"{p}: is a directory; give an output file name")
        if is_folder and p.exists() and not p.is_dir():
            raise InputError(f"{p}: exists and is not a folder")
    probed: set[Path] = set()
    for p, is_folder in outs:
        anc = p if is_folder and p.is_dir() else p.parent
        while not anc.exists() and anc != anc.parent:
            anc = anc.parent
        if anc in probed:
            continue
        if not anc.is_dir():
            raise InputError(f"{p}: {anc} is a file, not a folder")
        try:
            fd, tmp = tempfile.mkstemp(prefix=".prism3d-write-check.", dir=anc)
            os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            raise InputError(f"{p}: cannot write in {anc} ({exc.strerror or exc})") from None
        probed.add(anc)


@contextlib.contextmanager
def atomic_paths(*paths: str | Path) -> Iterator[list[Path]]:
    """Temporary paths beside each of ``paths``, moved onto them together when the block
    succeeds (one command's several files appear together); on any exception every temp
    file is removed and no target is touched. Two names for one file are refused."""
    targets = [Path(p) for p in paths]
    if len({t.resolve() for t in targets}) != len(targets):
        raise InputError(f"outputs: two of {', '.join(map(str, targets))} name the same file")
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(atomic_path(t)) for t in targets]


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """Open a temp file for writing; it replaces ``path`` when the block succeeds."""
    if "w" not in mode:
        raise ValueError("atomic_open is for writing")
    with atomic_path(path) as tmp:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))



def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


@contextlib.contextmanager
def output_lock(target: str | Path) -> Iterator[Path]:
    """Own the output folder ``target`` while it is written: a lock file beside it
    (``.NAME.lock``: this process's host and pid) that a second writer sees and is
    refused by with one line. A lock left by a dead process of this host is taken over,
    and the staging folders it lists are removed. Yields the lock's path."""

    t = Path(target)
    lock = t.parent / f".{t.name}.lock"
    me = {"host": socket.gethostname(), "pid": os.getpid(), "stages": []}
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                other = json.loads(lock.read_text())
                host, pid = str(other["host"]), int(other["pid"])
            except (OSError, ValueError, KeyError, TypeError):
                host, pid, other = me["host"], -1, {}  # unreadable: a writer died mid-write
            if host != me["host"] or (pid > 0 and _alive(pid)):
                raise InputError(f"{t}: another prism3d process ({host}, pid {pid}) is writing it; wait for it "
                                 f"or give another output (a lock left by a crash: remove {lock})") from None
            for st in other.get("stages", []) if isinstance(other.get("stages"), list) else []:
                sp = Path(str(st))
                if sp.parent == t.parent and sp.name.startswith(f".{t.name}.") and sp.name.endswith(".tmp"):
                    shutil.rmtree(sp, ignore_errors=True)  # the dead writer's half-written outputs
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()
            continue
        try:
            with os.fdopen(fd, "w") as f:
                f.write(json.dumps(me))
        except BaseException:  # a full disk: no lock left behind
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()
            raise
        break
    else:
        raise InputError(f"{t}: could not take its lock {lock}")
    try:
        yield lock
    finally:
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()


def _note_stage(lock: Path, stage: Path) -> None:
    """Record a staging folder in the lock, so a run after a crash can remove it."""
    doc = json.loads(lock.read_text())
    doc["stages"] = [*doc.get("stages", []), str(stage)]
    tmp = lock.with_name(lock.name + ".tmp")
    try:
        tmp.write_text(json.dumps(doc))
        os.replace(tmp, lock)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def staged_folder(out_dir: str | Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``out_dir`` to write a command's outputs into;
    on success they move into ``out_dir`` together (one rename when it does not exist
    yet), on any exception they are removed and ``out_dir`` is left as it was. The
    folder is owned while written (:func:`output_lock`): a second writer is refused."""
    target = Path(out_dir)
    if target.exists() and not target.is_dir():
        raise InputError(f"{target}: exists and is not a folder")
    target.parent.mkdir(parents=True, exist_ok=True)
    with output_lock(target) as lock:
        stage = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
        try:
            _note_stage(lock, stage)
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
        with _staged(stage, target):
            yield stage


@contextlib.contextmanager
def _staged(stage: Path, target: Path) -> Iterator[None]:
    mask = os.umask(0)
    os.umask(mask)
    stage.chmod(0o777 & ~mask)  # as a folder made by mkdir would be, not mkdtemp's 0700
    try:
        try:
            yield
        except (OSError, Prism3dError) as exc:  # name the output, not the staging folder
            renamed = _renamed(exc, str(stage), str(target))
            if renamed is exc:
                raise
            raise renamed from exc
        if not target.exists():
            os.replace(stage, target)
            return
        for src in sorted(stage.rglob("*"), key=lambda p: len(p.parts)):  # folders before their files
            dst = target / src.relative_to(stage)
            if src.is_dir():
                dst.mkdir(exist_ok=True)
            else:
                os.replace(src, dst)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _renamed(exc: BaseException, old: str, new: str) -> BaseException:
    """``exc`` with the path prefix ``old`` replaced by ``new`` in its file name or
    message, or ``new`` as the file name of an OSError that has none (the same
    exception when there is nothing to change)."""
    if isinstance(exc, OSError):
        if exc.filename is None:  # a library's OSError without a file: say which output
            return OSError(exc.errno or 0, exc.strerror or str(exc), new)
        if old in str(exc.filename):
            return OSError(exc.errno or 0, exc.strerror or str(exc), str(exc.filename).replace(old, new))
        return exc
    msg = str(exc)
    if old not in msg:
        return exc
    try:
        return type(exc)(msg.replace(old, new))
    except TypeError:  # a subclass with another signature: keep it as it is
        return exc
