"""A simulated trigger controller speaking the line protocol on a real pseudo-terminal.

The host opens the pty slave path (e.g. ``/dev/pts/5``) with pyserial as it would
``/dev/ttyACM0``. Injectable faults (:data:`FAULTS`, described in
docs/trigger-protocol.md and docs/capture.md): None, ``silence``, ``garbage``,
``drop``, ``disconnect`` (comes back on a new pty, ``link`` re-pointed) and ``slow``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import random
import select
import signal
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from prism3d.capture.trigger_protocol import (
    ERROR_CODES,
    PROTOCOL_VERSION,
    FrameError,
    LineParser,
    Message,
    encode,
)
from prism3d.errors import DeviceError, InputError

__all__ = ["FAULTS", "SimulatedDevice", "run_simulator", "TriggerSimulator", "simulate_main"]

log = logging.getLogger(__name__)

#: Fault names accepted by :func:`run_simulator` (``None`` = no fault).
FAULTS = (None, "silence", "garbage", "drop", "disconnect", "slow")

#: Limits enforced by the device (microseconds).
MAX_SHUTTER_US = 1_000_000
MAX_FLASH_US = 100_000
MAX_PATTERN = 15
#: Seconds between answering the first command and closing the pty ("disconnect").
_DISCONNECT_HOLDOFF_S = 0.2


def _check_fault(fault: str | None) -> str | None:
    if fault not in FAULTS:
        names = ", ".join(str(f) for f in FAULTS[1:])
        raise InputError(f"fault: expected none or one of {names}; got {fault!r}")
    return fault


class SimulatedDevice:
    """The device's protocol logic as a pure state machine: ``clock_us`` (device clock,
    us since boot; default monotonic), ``sleep`` (waits out the exposure), ``serial``
    (reported by ``ID``).
    """

    def __init__(
        self,
        *,
        clock_us: Callable[[], int] | None = None,
        sleep: Callable[[float], None] = time.sleep,
        serial: str = "SIM-0001",
    ) -> None:
        t0 = time.monotonic_ns()
        self._clock = clock_us or (lambda: (time.monotonic_ns() - t0) // 1000)
        self._sleep = sleep
        self.serial = serial
        self.armed = False
        self.pattern = 0
        self.shots = 0
        self.last_shutter_us = -1
        self.last_flash_us = -1
        self._events = 0
        self._last_cmd: tuple[int, str, tuple[str, ...]] | None = None
        self._last_out: list[bytes] = []

    def _reply(self, seq: int, *args: object) -> bytes:
        return encode(seq, "OK", *args)

    def _err(self, seq: int, code: int) -> bytes:
        return encode(seq, "ERR", code, ERROR_CODES[code].replace(" ", "_"))

    def _event(self, *args: object) -> bytes:
        self._events = self._events % 65535 + 1
        return encode(self._events, "EV", *args)

    def handle(self, item: Message | FrameError) -> list[bytes]:
        """Process one parsed line; return the lines to send (reply, then events)."""
        if isinstance(item, FrameError):
            seq = item.seq if item.seq is not None else 0
            if item.reason == "checksum error":
                return [self._err(seq, 1)]
            if item.reason == "overlong line":
                return [self._err(0, 7)]
            return [self._err(seq, 2)]
        key = (item.seq, item.word, item.args)
        if key == self._last_cmd and item.seq != 0:
            # A retry of the command just executed: answer again, do not re-execute.
            return list(self._last_out)
        out = self._execute(item)
        self._last_cmd, self._last_out = key, out
        return out

    def _int_args(self, args: tuple[str, ...], n: int) -> list[int] | None:
        if len(args) != n:
            return None
        try:
            return [int(a, 10) for a in args]
        except ValueError:
            return None

    def _execute(self, m: Message) -> list[bytes]:
        seq = m.seq
        if m.word == "ID" and not m.args:
            return [
                self._reply(seq, "ID", "model=PRISM3D-TRIG", "fw=1.0.0",
                            f"proto={PROTOCOL_VERSION}", f"serial={self.serial}")
            ]
        if m.word == "STATUS" and not m.args:
            return [
                self._reply(
                    seq, "STATUS", f"armed={int(self.armed)}", f"pattern={self.pattern}",
                    f"shots={self.shots}", f"t_shutter_us={self.last_shutter_us}",
                    f"t_flash_us={self.last_flash_us}", "temp_c=31.5",
                    f"uptime_us={self._clock()}",
                )
            ]
        if m.word == "ARM":
            vals = self._int_args(m.args, 1)
            if vals is None or not 0 <= vals[0] <= MAX_PATTERN:
                return [self._err(seq, 4)]
            self.armed, self.pattern = True, vals[0]
            return [self._reply(seq, "ARM", f"pattern={self.pattern}")]
        if m.word == "DISARM" and not m.args:
            self.armed = False
            return [self._reply(seq, "DISARM")]
        if m.word == "FIRE":
            vals = self._int_args(m.args, 3)
            if vals is None:
                return [self._err(seq, 4)]
            delay, flash, shutter = vals
            if not (
                1 <= shutter <= MAX_SHUTTER_US
                and 0 <= flash <= MAX_FLASH_US
                and 0 <= delay
                and delay + flash <= shutter
            ):
                return [self._err(seq, 4)]
            if not self.armed:
                return [self._err(seq, 3)]
            self.shots += 1
            shot = self.shots
            ack = self._reply(seq, "FIRE", f"shot={shot}")
            t_open = self._clock() + 200  # shutter opens 200 us after the command
            self._sleep((200 + shutter) / 1e6)
            self.last_shutter_us = t_open
            self.last_flash_us = t_open + delay if flash > 0 else -1
            self.armed = False
            ev = self._event(
                "FIRED", f"shot={shot}", f"pattern={self.pattern}",
                f"t_shutter_us={self.last_shutter_us}", f"t_flash_us={self.last_flash_us}",
                f"shutter_us={shutter}", f"flash_us={flash}",
            )
            return [ack, ev]
        return [self._err(seq, 2)]


def _check_link(link: str | Path | None) -> Path | None:
    """The link path; InputError when something other than a symlink is there (a link
    only ever replaces a link: the file would be lost)."""
    if link is None:
        return None
    p = Path(link)
    if p.exists() and not p.is_symlink():
        raise InputError(f"--link {p}: exists and is not a symlink; refusing to replace it")
    return p


def _point_link(link: Path, target: str) -> None:
    tmp = link.with_name(f".{link.name}.tmp{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    os.symlink(target, tmp)
    os.replace(tmp, link)


def _send(master: int, data: bytes) -> None:
    """Write ``data`` to the pty master: dropped (logged) when its buffer is full, ignored
    once the pty is gone (EIO, EBADF)."""
    try:
        os.write(master, data)
    except BlockingIOError:
        log.debug("simulator output buffer full; dropped %r", data)
    except OSError as exc:
        if exc.errno not in (errno.EIO, errno.EBADF):
            raise


def _read_pty(master: int) -> bytes | None:
    """Bytes the host wrote, or None when there is nothing to read after all (the caller
    polls again)."""
    try:
        return os.read(master, 4096)
    except BlockingIOError:
        return None
    except OSError as exc:  # EIO: no process has the slave open (we hold it, so rare)
        if exc.errno == errno.EIO:
            time.sleep(0.02)
            return None
        raise


def _send_garbage(master: int, line: bytes, rng: random.Random) -> None:
    """The ``garbage`` fault for one device line: random junk or, as often, the line with a
    corrupted checksum."""
    if rng.random() < 0.5:
        junk = bytes(rng.randrange(256) for _ in range(rng.randint(4, 60)))
        _send(master, junk + b"\n")
    else:  # the real line with a corrupted checksum
        body = line[:-3]
        bad = (int(line[-3:-1], 16) ^ 0x5A) & 0xFF
        _send(master, body + b"%02X\n" % bad)


def _serve_connection(
    master: int,
    device: SimulatedDevice,
    fault: str | None,
    stop: threading.Event,
    rng: random.Random,
    slow_s: float,
) -> bool:
    """Serve one pty until ``stop`` (returns False) or a simulated disconnect (True)."""
    parser = LineParser()
    pending: list[tuple[float, bytes]] = []
    replies_seen = 0
    commands = 0
    while not stop.is_set():
        now = time.monotonic()
        due = [p for p in pending if p[0] <= now]
        pending = [p for p in pending if p[0] > now]
        for _, data in due:
            _send(master, data)
        wait = 0.05 if not pending else max(0.0, min(0.05, min(p[0] for p in pending) - now))
        r, _, _ = select.select([master], [], [], wait)
        if not r:
            continue
        data = _read_pty(master)
        if data is None:
            continue
        for item in parser.feed(data):
            out = device.handle(item)
            commands += 1
            for line in out:
                is_reply = b" EV " not in line
                if fault == "silence":
                    continue
                if fault == "garbage":
                    _send_garbage(master, line, rng)
                    continue
                if fault == "drop" and is_reply:
                    replies_seen += 1
                    if replies_seen % 2 == 1:
                        continue
                if fault == "slow":
                    pending.append((time.monotonic() + slow_s, line))
                    continue
                _send(master, line)
            if fault == "disconnect" and commands >= 1:
                # Let the host read the answer, then "reset" (close the pty).
                stop.wait(_DISCONNECT_HOLDOFF_S)
                return True
    return False


def run_simulator(
    *,
    fault: str | None = None,
    ready: Callable[[str], object] | None = None,
    stop: threading.Event | None = None,
    link: str | Path | None = None,
    slow_s: float = 1.5,
    reboot_s: float = 0.2,
    seed: int = 0,
) -> None:
    """Serve the trigger protocol on a new pty until ``stop`` is set (checked every 50 ms).

    ``fault`` one of :data:`FAULTS`; ``ready(path)`` is called each time a pty is ready
    (again after each simulated disconnect); ``link`` a symlink kept pointing at the
    current pty; ``slow_s`` the ``slow`` reply delay and ``reboot_s`` the absence after
    a ``disconnect``, s; ``seed`` seeds the ``garbage`` bytes. InputError for an
    unknown fault.
    """
    _check_fault(fault)
    link_path = _check_link(link)
    stop = stop or threading.Event()
    rng = random.Random(seed)
    device = SimulatedDevice()
    while not stop.is_set():
        master, slave = os.openpty()
        try:
            tty.setraw(slave)
            flags = fcntl.fcntl(master, fcntl.F_GETFL)
            fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
            path = os.ttyname(slave)
            if link_path is not None:
                _point_link(link_path, path)
            log.info("trigger simulator on %s (fault=%s)", path, fault)
            if ready is not None:
                ready(path)
            disconnected = _serve_connection(master, device, fault, stop, rng, slow_s)
        finally:
            if link_path is not None:
                with contextlib.suppress(FileNotFoundError):
                    link_path.unlink()
            os.close(master)
            os.close(slave)
        if not disconnected:
            break
        log.info("simulated disconnect of %s", path)
        stop.wait(reboot_s)


class TriggerSimulator:
    """Run :func:`run_simulator` in a daemon thread (tests, demos), as a context manager::

        with TriggerSimulator(fault="drop") as sim:
            with TriggerClient(sim.port, timeout=0.3) as trig:
                trig.identify()

    ``fault, link, slow_s, reboot_s, seed`` as in :func:`run_simulator`;
    ``start_timeout`` s to wait for the pty.
    """

    def __init__(
        self,
        fault: str | None = None,
        *,
        link: str | Path | None = None,
        slow_s: float = 1.5,
        reboot_s: float = 0.2,
        seed: int = 0,
        start_timeout: float = 5.0,
    ) -> None:
        self.fault = _check_fault(fault)
        self.link = _check_link(link)
        self._kw = dict(fault=fault, link=link, slow_s=slow_s, reboot_s=reboot_s, seed=seed)
        self._start_timeout = start_timeout
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._ports: list[str] = []
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def port(self) -> str:
        """Path of the current pty slave (changes after a simulated disconnect)."""
        if not self._ports:
            raise DeviceError("trigger simulator is not running")
        return self._ports[-1]

    @property
    def ports(self) -> list[str]:
        """Every pty path served so far, oldest first."""
        return list(self._ports)

    def _on_ready(self, path: str) -> None:
        self._ports.append(path)
        self._ready.set()

    def _run(self) -> None:
        try:
            run_simulator(ready=self._on_ready, stop=self._stop, **self._kw)  # type: ignore[arg-type]
        except BaseException as exc:  # reported by start()/stop()
            self._error = exc
            self._ready.set()

    def start(self) -> TriggerSimulator:
        """Start the background thread and wait until the pty exists."""
        if self._thread is not None:
            return self
        self._thread = threading.Thread(target=self._run, name="trigger-sim", daemon=True)
        self._thread.start()
        if not self._ready.wait(self._start_timeout) or self._error is not None:
            self.stop()
            raise DeviceError(f"trigger simulator did not start: {self._error or 'timeout'}")
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop serving and join the thread (bounded by ``timeout``)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def __enter__(self) -> TriggerSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def simulate_main(
    fault: str | None = None,
    out: TextIO | None = None,
    *,
    link: str | Path | None = None,
    stop: threading.Event | None = None,
) -> int:
    """Entry point of ``prism3d trigger simulate [--fault F] [--link PATH]``: prints the
    pty path as the first stdout line (flushed), one line per new pty after a
    disconnect, and serves until SIGINT/SIGTERM or ``stop`` is set; returns 0.
    """
    import sys

    _check_fault(fault)
    stream = out if out is not None else sys.stdout
    stop = stop if stop is not None else threading.Event()

    def announce(path: str) -> None:
        print(path, file=stream, flush=True)

    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        run_simulator(fault=fault, ready=announce, stop=stop, link=link)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
    return 0
