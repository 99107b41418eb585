"""Host client of the flash/shutter trigger controller over a serial line (pyserial):
protocol in docs/trigger-protocol.md, framing in :mod:`prism3d.capture.trigger_protocol`.
Calls are bounded (``timeout`` per try, ``1 + retries`` tries with the same sequence
number, so a retried ``FIRE`` never fires twice); failures raise DeviceError.
"""

from __future__ import annotations

import collections
import logging
import secrets
import time
from dataclasses import asdict, dataclass
from typing import Any

import serial

from prism3d.capture.trigger_protocol import (
    ERROR_CODES,
    MAX_SEQ,
    PROTOCOL_VERSION,
    FrameError,
    LineParser,
    Message,
    encode,
    parse_kv,
)
from prism3d.checks import check_in_range, check_positive
from prism3d.errors import DeviceError, InputError

__all__ = [
    "DeviceInfo",
    "FireReport",
    "TriggerStatus",
    "TriggerClient",
    "trigger_ping",
    "trigger_status",
    "trigger_fire",
    "DEFAULT_SHUTTER_US",
    "DEFAULT_FLASH_US",
    "DEFAULT_FLASH_DELAY_US",
]

log = logging.getLogger(__name__)

#: Default exposure: 1/125 s, inside the paper's "< 1/100 s" single-flash capture.
DEFAULT_SHUTTER_US = 8000
#: Default flash duration and its delay after the shutter opens.
DEFAULT_FLASH_US = 2000
DEFAULT_FLASH_DELAY_US = 500

_POLL_S = 0.02


#: Longest wait for a reply or a reconnection, s: an hour; a serial device that takes
#: longer is not answering (and 1e300 overflows the port's timer).
MAX_TIMEOUT_S = 3600.0


@dataclass(frozen=True)
class DeviceInfo:
    """Answer to ``ID``."""

    model: str
    firmware: str
    protocol: int
    serial: str


@dataclass(frozen=True)
class FireReport:
    """What the controller did for one ``FIRE`` (device us): ``shot`` counter, ``pattern_id``,
    ``t_shutter_us``, ``t_flash_us`` (None without flash), ``shutter_us, flash_us, flash_delay_us``.
    """

    shot: int
    pattern_id: int
    t_shutter_us: int
    t_flash_us: int | None
    shutter_us: int
    flash_us: int
    flash_delay_us: int

    @property
    def flash_fired(self) -> bool:
        """True when the flash fired during the exposure."""
        return self.t_flash_us is not None and self.flash_us > 0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (adds ``flash_fired``)."""
        d = asdict(self)
        d["flash_fired"] = self.flash_fired
        return d


@dataclass(frozen=True)
class TriggerStatus:
    """Answer to ``STATUS``: arming state, counters, last fire timestamps."""

    armed: bool
    pattern_id: int
    shots: int
    t_shutter_us: int | None
    t_flash_us: int | None
    temp_c: float
    uptime_us: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


def _check_us(value: int, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise InputError(f"{name}: expected an integer in [{lo}, {hi}] microseconds, got {value!r}")
    return value


class TriggerClient:
    """Talk to a trigger controller on any pyserial URL ``url``: ``timeout`` s per
    reply and try, ``retries`` extra tries after a timeout or corrupted reply,
    ``baudrate`` (115200 8N1). DeviceError when the port cannot be opened.
    """

    def __init__(
        self, url: str, *, timeout: float = 1.0, retries: int = 2, baudrate: int = 115200
    ) -> None:
        self.url = str(url)
        self.timeout = check_in_range(check_positive(timeout, "timeout"), "timeout", 0.0, MAX_TIMEOUT_S)
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
            raise InputError(f"retries: expected an integer >= 0, got {retries!r}")
        self.retries = retries
        self.baudrate = int(check_positive(baudrate, "baudrate"))
        self._ser: serial.SerialBase | None = None
        self._parser = LineParser()
        # a random start: a late reply from an earlier process (which also started
        # somewhere) does not carry the sequence number this one waits for
        self._seq = secrets.randbelow(MAX_SEQ)
        self._events: collections.deque[Message] = collections.deque(maxlen=64)
        self.open()

    # -- connection -------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._ser is not None

    def open(self) -> None:
        """Open the port (no-op when already open)."""
        if self._ser is not None:
            return
        try:
            ser = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=_POLL_S,
                write_timeout=self.timeout,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open trigger port {self.url}: {exc}") from exc
        self._ser = ser
        self._parser.reset()
        self._discard_input()

    def close(self) -> None:
        """Close the port (safe to call twice)."""
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError) as exc:
                log.debug("closing %s: %s", self.url, exc)

    def reconnect(self, timeout: float = 5.0) -> None:
        """Close and reopen the port, waiting up to ``timeout`` s for it to reappear
        (after "port vanished"; use the stable ``/dev/serial/by-id`` name).
        """
        self.close()
        deadline = time.monotonic() + check_in_range(check_positive(timeout, "timeout"), "timeout", 0.0,
                                                     MAX_TIMEOUT_S)
        while True:
            try:
                self.open()
                return
            except DeviceError:
                if time.monotonic() >= deadline:
                    raise DeviceError(
                        f"cannot reconnect to trigger port {self.url} within {timeout} s"
                    ) from None
                time.sleep(0.05)

    def __enter__(self) -> TriggerClient:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- low level --------------------------------------------------------------------

    def _vanished(self, exc: BaseException) -> DeviceError:
        self.close()
        return DeviceError(f"port vanished: {self.url} ({exc}); reconnect when the device is back")

    def _port(self) -> serial.SerialBase:
        if self._ser is None:
            raise DeviceError(f"trigger port {self.url} is closed; open or reconnect first")
        return self._ser

    def _read_items(self) -> list[Message | FrameError]:
        ser = self._port()
        try:
            data = ser.read(max(1, ser.in_waiting))
        except (serial.SerialException, OSError) as exc:
            raise self._vanished(exc) from exc
        return self._parser.feed(data) if data else []

    def _stash_events(self, items: list[Message | FrameError]) -> list[Message | FrameError]:
        """Keep the events of a batch of lines (a reply and its event often arrive in
        one read: returning on the reply must not drop the event); return the rest."""
        rest = []
        for item in items:
            if isinstance(item, Message) and item.is_event:
                self._events.append(item)
            else:
                rest.append(item)
        return rest

    def _discard_input(self) -> None:
        """Drop stale bytes and replies before a new command (events are kept)."""
        ser = self._port()
        try:
            waiting = ser.in_waiting
            data = ser.read(waiting) if waiting else b""
        except (serial.SerialException, OSError) as exc:
            raise self._vanished(exc) from exc
        for item in self._parser.feed(data):
            if isinstance(item, Message) and item.is_event:
                self._events.append(item)
        self._parser.reset()

    def _next_seq(self) -> int:
        self._seq = self._seq % MAX_SEQ + 1
        return self._seq

    def request(self, word: str, *args: object) -> Message:
        """Send one command and return its ``OK`` reply; DeviceError after ``1 + retries``
        tries without a valid reply, on ``ERR``, or a vanished port.
        """
        line = encode(self._next_seq(), word, *args)
        seq = self._seq
        tries = 1 + self.retries
        corrupted: collections.Counter[str] = collections.Counter()
        last_problem = ""
        self._discard_input()
        for attempt in range(tries):
            ser = self._port()
            try:
                ser.write(line)
                ser.flush()
            except serial.SerialTimeoutException as exc:
                raise DeviceError(f"cannot write to trigger port {self.url}: {exc}") from exc
            except (serial.SerialException, OSError) as exc:
                raise self._vanished(exc) from exc
            deadline = time.monotonic() + self.timeout
            while time.monotonic() < deadline:
                for item in self._stash_events(self._read_items()):
                    if isinstance(item, FrameError):
                        corrupted[item.reason] += 1
                        log.debug("%s: %s in %r", self.url, item.reason, item.raw)
                        continue
                    if item.seq != seq or not item.is_reply:
                        log.debug("%s: ignoring stale line %s", self.url, item)
                        continue
                    if item.word == "OK":
                        if not item.args or item.args[0] != word:  # a reply to another command
                            log.debug("%s: ignoring reply %s to a command other than %s", self.url, item, word)
                            continue
                        return item
                    code, text = self._error_of(item)
                    if code == 1 and attempt + 1 < tries:  # our line was garbled: resend
                        last_problem = "device saw a checksum error"
                        break
                    raise DeviceError(
                        f"{self.url}: device reported ERR {code}: {text} (command {word})"
                    )
                else:
                    continue
                break
            log.info("%s: no valid reply to %s (try %d/%d)", self.url, word, attempt + 1, tries)
            self._parser.reset()
        what = f"no reply from {self.url} to {word} within {self.timeout:g} s after {tries} tries"
        if corrupted:
            kinds = ", ".join(f"{n} {reason}" for reason, n in sorted(corrupted.items()))
            what = (
                f"no valid reply from {self.url} to {word} within {self.timeout:g} s after "
                f"{tries} tries; {corrupted.total()} corrupted line(s) received ({kinds})"
            )
        elif last_problem:
            what += f" ({last_problem})"
        raise DeviceError(what)

    @staticmethod
    def _error_of(msg: Message) -> tuple[int, str]:
        try:
            code = int(msg.args[0])
        except (IndexError, ValueError):
            return -1, " ".join(msg.args) or "unspecified error"
        text = " ".join(msg.args[1:]).replace("_", " ") or ERROR_CODES.get(code, "unknown error")
        return code, text

    def _wait_event(self, kind: str, key: str, value: str, timeout: float) -> Message | None:
        deadline = time.monotonic() + timeout
        while True:
            for ev in list(self._events):
                if ev.args and ev.args[0] == kind and parse_kv(ev.args[1:]).get(key) == value:
                    self._events.remove(ev)
                    return ev
            if time.monotonic() >= deadline:
                return None
            for item in self._read_items():
                if isinstance(item, Message) and item.is_event:
                    self._events.append(item)

    # -- commands ---------------------------------------------------------------------

    def identify(self) -> DeviceInfo:
        """``ID``: model, firmware, protocol version and serial number (DeviceError also
        for another protocol version).
        """
        kv = parse_kv(self.request("ID").args[1:])
        try:
            info = DeviceInfo(kv["model"], kv["fw"], int(kv["proto"]), kv.get("serial", ""))
        except (KeyError, ValueError) as exc:
            raise DeviceError(f"{self.url}: malformed ID reply {kv}") from exc
        if info.protocol != PROTOCOL_VERSION:
            raise DeviceError(
                f"{self.url}: device speaks protocol {info.protocol}, "
                f"this host speaks {PROTOCOL_VERSION}; update the firmware or prism3d"
            )
        return info

    def arm(self, pattern_id: int = 1) -> None:
        """``ARM``: select the grating pattern (0 = plain flash, 1..15) and arm one shot."""
        _check_us(pattern_id, "pattern_id", 0, 15)
        self.request("ARM", pattern_id)

    def disarm(self) -> None:
        """``DISARM``."""
        self.request("DISARM")

    def status(self) -> TriggerStatus:
        """``STATUS``."""
        kv = parse_kv(self.request("STATUS").args[1:])
        try:
            ts, tf = int(kv["t_shutter_us"]), int(kv["t_flash_us"])
            return TriggerStatus(
                armed=kv["armed"] == "1",
                pattern_id=int(kv["pattern"]),
                shots=int(kv["shots"]),
                t_shutter_us=ts if ts >= 0 else None,
                t_flash_us=tf if tf >= 0 else None,
                temp_c=float(kv.get("temp_c", "nan")),
                uptime_us=int(kv.get("uptime_us", "0")),
            )
        except (KeyError, ValueError) as exc:
            raise DeviceError(f"{self.url}: malformed STATUS reply {kv}") from exc

    def fire(
        self,
        *,
        flash_delay_us: int = DEFAULT_FLASH_DELAY_US,
        flash_us: int = DEFAULT_FLASH_US,
        shutter_us: int = DEFAULT_SHUTTER_US,
    ) -> FireReport:
        """``FIRE``: open the shutter for ``shutter_us`` and fire the flash inside it
        (``flash_us = 0``: no flash). Waits for ``FIRED`` (``timeout`` plus the exposure),
        else asks ``STATUS``. InputError for bad timings; DeviceError if not armed, no
        reply or the port vanished.
        """
        _check_us(shutter_us, "shutter_us", 1, 1_000_000)
        _check_us(flash_us, "flash_us", 0, 100_000)
        _check_us(flash_delay_us, "flash_delay_us", 0, 1_000_000)
        if flash_delay_us + flash_us > shutter_us:
            raise InputError(
                f"flash_delay_us + flash_us = {flash_delay_us + flash_us} exceeds "
                f"shutter_us = {shutter_us}: the flash must fire while the shutter is open"
            )
        ack = self.request("FIRE", flash_delay_us, flash_us, shutter_us)
        shot_text = parse_kv(ack.args[1:]).get("shot", "")
        ev = self._wait_event("FIRED", "shot", shot_text, self.timeout + shutter_us / 1e6)
        if ev is not None:
            kv = parse_kv(ev.args[1:])
            try:
                tf = int(kv["t_flash_us"])
                return FireReport(
                    shot=int(kv["shot"]), pattern_id=int(kv["pattern"]),
                    t_shutter_us=int(kv["t_shutter_us"]), t_flash_us=tf if tf >= 0 else None,
                    shutter_us=int(kv["shutter_us"]), flash_us=int(kv["flash_us"]),
                    flash_delay_us=flash_delay_us,
                )
            except (KeyError, ValueError) as exc:
                raise DeviceError(f"{self.url}: malformed FIRED event {ev}") from exc
        log.info("%s: FIRED event for shot %s lost; asking STATUS", self.url, shot_text)
        st = self.status()
        if str(st.shots) != shot_text or st.t_shutter_us is None:
            raise DeviceError(
                f"{self.url}: FIRE acknowledged (shot {shot_text}) but the device never "
                f"confirmed the exposure (status shots={st.shots})"
            )
        return FireReport(
            shot=st.shots, pattern_id=st.pattern_id, t_shutter_us=st.t_shutter_us,
            t_flash_us=st.t_flash_us, shutter_us=shutter_us, flash_us=flash_us,
            flash_delay_us=flash_delay_us,
        )


# -- library functions behind `prism3d trigger ping|status|fire PORT` ----------------------


def trigger_ping(port: str, timeout: float = 1.0) -> dict[str, Any]:
    """``prism3d trigger ping PORT``: ``port, model, firmware, protocol, serial,
    round_trip_ms``.
    """
    with TriggerClient(port, timeout=timeout) as trig:
        t0 = time.perf_counter()
        info = trig.identify()
        rtt = (time.perf_counter() - t0) * 1e3
    return {"port": port, **asdict(info), "round_trip_ms": round(rtt, 3)}


def trigger_status(port: str, timeout: float = 1.0) -> dict[str, Any]:
    """``prism3d trigger status PORT``: the controller's ``STATUS`` as a dict."""
    with TriggerClient(port, timeout=timeout) as trig:
        return {"port": port, **trig.status().to_dict()}


def trigger_fire(
    port: str,
    *,
    pattern_id: int = 1,
    flash_delay_us: int = DEFAULT_FLASH_DELAY_US,
    flash_us: int = DEFAULT_FLASH_US,
    shutter_us: int = DEFAULT_SHUTTER_US,
    timeout: float = 1.0,
) -> dict[str, Any]:
    """``prism3d trigger fire PORT``: arm ``pattern_id``, fire once; ``port`` plus
    :meth:`FireReport.to_dict`.
    """
    with TriggerClient(port, timeout=timeout) as trig:
        trig.arm(pattern_id)
        report = trig.fire(flash_delay_us=flash_delay_us, flash_us=flash_us, shutter_us=shutter_us)
    return {"port": port, **report.to_dict()}
