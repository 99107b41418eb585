"""Host client against the simulated controller on a REAL pty (pyserial), with faults."""

from __future__ import annotations

import io
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from prism3d.capture.trigger import (
    TriggerClient,
    trigger_fire,
    trigger_ping,
    trigger_status,
)
from prism3d.capture.trigger_protocol import FrameError, LineParser, Message, encode
from prism3d.capture.trigger_sim import (
    SimulatedDevice,
    TriggerSimulator,
    run_simulator,
    simulate_main,
)
from prism3d.errors import DeviceError, InputError

TIMEOUT = 0.3


@pytest.fixture
def sim() -> Iterator[TriggerSimulator]:
    s = TriggerSimulator()
    s.start()
    try:
        yield s
    finally:
        s.stop()


def test_port_is_a_real_pty(sim: TriggerSimulator) -> None:
    assert sim.port.startswith("/dev/pts/")
    assert os.path.exists(sim.port)


def test_identify_arm_fire_status(sim: TriggerSimulator) -> None:
    with TriggerClient(sim.port, timeout=TIMEOUT) as trig:
        info = trig.identify()
        assert info.model == "PRISM3D-TRIG" and info.protocol == 1
        assert not trig.status().armed
        trig.arm(3)
        st = trig.status()
        assert st.armed and st.pattern_id == 3 and st.shots == 0 and st.t_shutter_us is None
        rep = trig.fire(flash_delay_us=1000, flash_us=2000, shutter_us=5000)
        assert rep.shot == 1 and rep.pattern_id == 3 and rep.flash_fired
        assert rep.t_flash_us - rep.t_shutter_us == 1000
        st = trig.status()
        assert not st.armed and st.shots == 1 and st.t_shutter_us == rep.t_shutter_us
        d = rep.to_dict()
        assert d["flash_fired"] is True and d["shutter_us"] == 5000
        trig.arm(0)
        rep2 = trig.fire(flash_us=0, flash_delay_us=0, shutter_us=1000)
        assert rep2.shot == 2 and not rep2.flash_fired and rep2.t_flash_us is None
        assert rep2.t_shutter_us > rep.t_shutter_us
        trig.arm(1)
        trig.disarm()
        assert not trig.status().armed
    assert not trig.is_open


def test_fire_without_arm_reports_device_error(sim: TriggerSimulator) -> None:
    with TriggerClient(sim.port, timeout=TIMEOUT) as trig:
        with pytest.raises(DeviceError, match=r"device reported ERR 3: not armed"):
            trig.fire()


def test_device_error_for_bad_command(sim: TriggerSimulator) -> None:
    with TriggerClient(sim.port, timeout=TIMEOUT) as trig:
        with pytest.raises(DeviceError, match=r"ERR 2: unknown command"):
            trig.request("SELFDESTRUCT")
        with pytest.raises(DeviceError, match=r"ERR 4: bad argument"):
            trig.request("ARM", 99)


def test_fire_argument_checks(sim: TriggerSimulator) -> None:
    with TriggerClient(sim.port, timeout=TIMEOUT) as trig:
        with pytest.raises(InputError, match="flash must fire while the shutter is open"):
            trig.fire(flash_delay_us=5000, flash_us=5000, shutter_us=8000)
        with pytest.raises(InputError, match="shutter_us"):
            trig.fire(shutter_us=0)
        with pytest.raises(InputError, match="pattern_id"):
            trig.arm(16)


def test_client_argument_checks() -> None:
    with pytest.raises(InputError, match="timeout"):
        TriggerClient("loop://", timeout=0)
    with pytest.raises(InputError, match="retries"):
        TriggerClient("loop://", retries=-1)


def test_cannot_open_missing_port(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match=r"cannot open trigger port .*nope"):
        TriggerClient(str(tmp_path / "nope"))


def test_closed_client_raises(sim: TriggerSimulator) -> None:
    trig = TriggerClient(sim.port, timeout=TIMEOUT)
    trig.close()
    trig.close()
    with pytest.raises(DeviceError, match="is closed"):
        trig.identify()


def test_loop_url_times_out_on_own_echo() -> None:
    # loop:// echoes our own command back: a valid line with our seq but not a reply.
    t0 = time.monotonic()
    with TriggerClient("loop://", timeout=0.1, retries=1) as trig:
        with pytest.raises(DeviceError, match=r"no reply from loop:// to ID within 0.1 s after 2 tries"):
            trig.identify()
    assert time.monotonic() - t0 < 1.0


@pytest.mark.parametrize(
    ("fault", "match"),
    [
        ("silence", r"no reply from /dev/pts/\d+ to ID within 0.3 s after 3 tries"),
        ("slow", r"no reply from /dev/pts/\d+ to ID within 0.3 s after 3 tries"),
        ("garbage", r"no valid reply from .* after 3 tries; \d+ corrupted line\(s\) received"),
    ],
)
def test_faults_end_in_device_error_within_timeout(fault: str, match: str) -> None:
    with TriggerSimulator(fault, slow_s=1.5) as s:
        with TriggerClient(s.port, timeout=TIMEOUT, retries=2) as trig:
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match=match):
                trig.identify()
            elapsed = time.monotonic() - t0
    assert 0.85 < elapsed < 0.3 * 3 + 0.5


def test_garbage_reports_checksum_errors() -> None:
    with TriggerSimulator("garbage", seed=3) as s:
        with TriggerClient(s.port, timeout=0.15, retries=5) as trig:
            with pytest.raises(DeviceError, match=r"after 6 tries; \d+ corrupted line\(s\) received \(\d+ checksum error"):
                trig.status()  # seeded: half the replies come back with a corrupted checksum


def test_drop_recovered_by_retry_and_fails_without() -> None:
    with TriggerSimulator("drop") as s:
        with TriggerClient(s.port, timeout=0.2, retries=0) as trig:
            with pytest.raises(DeviceError, match=r"no reply from .* to ID within 0.2 s after 1 tries"):
                trig.identify()  # reply 1 dropped
        with TriggerClient(s.port, timeout=0.2, retries=2) as trig:
            trig.identify()  # reply 3 dropped, the retry (same seq) is answered from cache
            trig.arm(1)
            rep = trig.fire()
            st = trig.status()
    assert rep.shot == 1 and st.shots == 1  # the retried FIRE did not fire twice


def test_disconnect_then_reconnect(tmp_path: Path) -> None:
    link = tmp_path / "ttyTRIG"
    with TriggerSimulator("disconnect", link=link, reboot_s=0.2) as s:
        with TriggerClient(str(link), timeout=TIMEOUT) as trig:
            assert trig.identify().serial == "SIM-0001"
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match=r"port vanished: .*ttyTRIG"):
                trig.status()
                trig.status()
            assert time.monotonic() - t0 < 1.0
            assert not trig.is_open
            trig.reconnect(timeout=3.0)
            assert trig.status().shots == 0
        assert len(s.ports) >= 2


def test_reconnect_gives_up(tmp_path: Path) -> None:
    with TriggerSimulator() as s:
        trig = TriggerClient(s.port, timeout=TIMEOUT)
    trig.url = str(tmp_path / "gone")
    with pytest.raises(DeviceError, match=r"cannot reconnect to trigger port .*gone within 0.2 s"):
        trig.reconnect(timeout=0.2)


def test_cli_functions(sim: TriggerSimulator) -> None:
    ping = trigger_ping(sim.port, timeout=TIMEOUT)
    assert ping["model"] == "PRISM3D-TRIG" and ping["round_trip_ms"] >= 0
    fired = trigger_fire(sim.port, pattern_id=2, timeout=TIMEOUT)
    assert fired["flash_fired"] and fired["pattern_id"] == 2
    st = trigger_status(sim.port, timeout=TIMEOUT)
    assert st["shots"] == 1 and st["armed"] is False


def test_device_answers_checksum_and_overlong_errors() -> None:
    dev = SimulatedDevice(sleep=lambda s: None)
    p = LineParser()
    bad = encode(9, "ID")[:-3] + b"00\n"
    (item,) = p.feed(bad)
    assert isinstance(item, FrameError)
    (reply,) = dev.handle(item)
    assert reply.startswith(b"9 ERR 1 checksum")
    (item,) = p.feed(b"z" * 200 + b"\n")
    assert dev.handle(item)[0].startswith(b"0 ERR 7")
    assert dev.handle(Message(1, "OK"))[0].startswith(b"1 ERR 2")
    assert dev.handle(Message(2, "FIRE", ("a", "b", "c")))[0].startswith(b"2 ERR 4")


def test_client_resends_after_device_checksum_error(sim: TriggerSimulator) -> None:
    # Inject one garbled byte on the wire by writing a broken line first: the client
    # must ignore the device's ERR 1 for seq 0 and still get its own answer.
    with TriggerClient(sim.port, timeout=TIMEOUT) as trig:
        trig._port().write(b"1 ID *00\n")
        assert trig.identify().model == "PRISM3D-TRIG"


def test_simulator_rejects_unknown_fault() -> None:
    with pytest.raises(InputError, match="fault: expected none or one of silence"):
        TriggerSimulator("fire")
    with pytest.raises(InputError, match="fault"):
        run_simulator(fault="boom")


def test_simulate_main_prints_port_first_and_stops() -> None:
    lines: list[str] = []
    printed = threading.Event()

    class Stream(io.StringIO):
        def write(self, text: str) -> int:
            lines.extend(text.splitlines())
            printed.set()
            return len(text)

    stop = threading.Event()
    result: list[int] = []
    th = threading.Thread(
        target=lambda: result.append(simulate_main(None, Stream(), stop=stop)), daemon=True
    )
    th.start()
    try:
        assert printed.wait(5)
        port = lines[0]
        assert port.startswith("/dev/pts/")
        with serial.serial_for_url(port, timeout=TIMEOUT) as ser:
            ser.write(encode(1, "ID"))
            assert b"1 OK ID" in ser.readline()
    finally:
        stop.set()
        th.join(3)
    assert result == [0]


def test_simulate_main_subprocess_sigterm(repo_root: Path) -> None:
    code = "import sys; from prism3d.capture.trigger_sim import simulate_main; sys.exit(simulate_main())"
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=repo_root
    )
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 20)
        assert ready, "simulator printed nothing"
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/pts/")
        assert trigger_ping(port, timeout=1.0)["protocol"] == 1
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        proc.stdout.close()


def test_link_never_replaces_a_file(tmp_path: Path) -> None:
    """``--link`` over an existing file is refused, the file kept; over a stale link it
    is re-pointed (a link loses nothing)."""
    f = tmp_path / "important.txt"
    f.write_text("keep me")
    with pytest.raises(InputError, match="exists and is not a symlink"):
        TriggerSimulator(link=f)
    r = subprocess.run([sys.executable, "-m", "prism3d.cli", "trigger", "simulate", "--link", str(f)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "refusing to replace" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert f.read_text() == "keep me"
    stale = tmp_path / "port"
    stale.symlink_to(tmp_path / "gone")
    with TriggerSimulator(link=stale) as sim:
        assert os.path.realpath(stale) == os.path.realpath(sim.port)
    assert not stale.exists() and not stale.is_symlink()  # removed on exit, as before


def test_fire_keeps_the_event_that_arrives_with_its_reply(sim: TriggerSimulator, caplog) -> None:
    """The plain simulator sends ``OK FIRE`` and the ``FIRED`` event in one write; the
    event was dropped with the rest of that read, and every FIRE then waited out its
    timeout and asked STATUS (1.3-1.4 s a shot)."""
    import logging

    with caplog.at_level(logging.INFO, logger="prism3d.capture.trigger"), TriggerClient(sim.port) as trig:
        for shot in (1, 2, 3):
            trig.arm(0)
            rep = trig.fire(flash_delay_us=100, flash_us=200, shutter_us=1000)
            assert rep.shot == shot and rep.t_flash_us == rep.t_shutter_us + 100
    assert "lost" not in caplog.text


def test_a_reply_to_another_command_is_not_taken(monkeypatch) -> None:
    """A reply with the right sequence number but for another command (a late answer
    from an earlier process) is ignored, and the call waits for its own."""
    from prism3d.capture import trigger as trig_mod
    from prism3d.capture.trigger_protocol import Message

    client = trig_mod.TriggerClient.__new__(trig_mod.TriggerClient)
    client.url, client.timeout, client.retries = "stub", 0.2, 0
    client._parser, client._events, client._seq = trig_mod.LineParser(), __import__("collections").deque(), 41
    sent = []

    class Port:
        def write(self, line): sent.append(line)
        def flush(self): pass

    batches = iter([[Message(42, "OK", ("ID", "model=X"))], [Message(42, "OK", ("STATUS", "armed=0"))]])
    monkeypatch.setattr(client, "_port", lambda: Port())
    monkeypatch.setattr(client, "_discard_input", lambda: None)
    monkeypatch.setattr(client, "_read_items", lambda: next(batches, []))
    assert client.request("STATUS").args[0] == "STATUS"
    assert sent and sent[0].startswith(b"42 STATUS")


def test_sequence_numbers_do_not_restart_at_1_per_process(sim: TriggerSimulator) -> None:
    starts = set()
    for _ in range(4):
        with TriggerClient(sim.port) as trig:
            starts.add(trig._seq)
    assert len(starts) > 1  # random starts (equal by chance with probability ~1e-14)


def test_a_late_reply_to_another_process_is_not_taken() -> None:
    """Two processes on one slow device: the first gives up on ID (three tries, replies
    2 s late); the second asks STATUS while those replies arrive, ignores them and
    returns its own answer."""
    import json
    import subprocess
    import sys

    with TriggerSimulator(fault="slow", slow_s=2.0) as sim:
        cli = [sys.executable, "-m", "prism3d.cli"]
        a = subprocess.run([*cli, "trigger", "ping", sim.port, "--timeout", "0.3"],
                           capture_output=True, text=True, timeout=60)
        assert a.returncode == 2 and "no reply" in a.stderr
        b = subprocess.run([*cli, "-vv", "trigger", "status", sim.port, "--timeout", "5"],
                           capture_output=True, text=True, timeout=60)
    assert b.returncode == 0, b.stderr
    assert "ignoring" in b.stderr  # the first process's late ID replies reached the second
    status = json.loads(b.stdout)
    assert status["armed"] is False and status["shots"] == 0

