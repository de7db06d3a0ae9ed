"""sd_notify over a REAL AF_UNIX datagram socket, as systemd's manager would receive it."""

import os
import signal
import socket
import struct
import subprocess
import sys
import time

import pytest

from thermod.runtime.sdnotify import Notifier


def _listener(address):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)  # systemd checks the sender's pid this way
    s.bind(address)
    s.settimeout(5.0)
    return s


def _recv(s):
    """(message lines, sender pid) from SCM_CREDENTIALS, as systemd's NotifyAccess=main check sees it."""
    data, anc, _, _ = s.recvmsg(4096, socket.CMSG_SPACE(struct.calcsize("3i")))
    pid = None
    for level, kind, payload in anc:
        if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
            pid, _uid, _gid = struct.unpack("3i", payload[:12])
    return data.decode().split("\n"), pid


def test_path_socket_messages(tmp_path):
    path = str(tmp_path / "notify")
    s = _listener(path)
    n = Notifier(env={"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready(status="50.0 fps\ngyro 1000 Hz")
    assert _recv(s) == (["READY=1", "STATUS=50.0 fps gyro 1000 Hz"], os.getpid())
    n.status("frames 49.9/s, deblurred 97 %")
    assert _recv(s)[0] == ["STATUS=frames 49.9/s, deblurred 97 %"]
    n.watchdog()
    assert _recv(s)[0] == ["WATCHDOG=1"]
    n.extend_timeout(2.5)
    assert _recv(s)[0] == ["EXTEND_TIMEOUT_USEC=2500000"]
    n.stopping()
    assert _recv(s)[0] == ["STOPPING=1"]
    assert n.sent == 5 and n.errors == 0
    n.close()
    s.close()


def test_abstract_socket():
    name = f"@thermod-test-{os.getpid()}-{time.monotonic_ns()}"
    s = _listener(b"\0" + name[1:].encode())
    n = Notifier(env={"NOTIFY_SOCKET": name})
    n.watchdog()
    assert _recv(s)[0] == ["WATCHDOG=1"]
    n.close()
    s.close()


def test_noop_outside_systemd_and_failures_never_raise(tmp_path):
    off = Notifier(env={})
    assert not off.enabled and off.ready() is False and off.watchdog() is False and off.sent == 0
    assert off.watchdog_usec() is None and off.watchdog_interval() is None
    gone = Notifier(env={"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert gone.ready() is False and gone.watchdog() is False
    assert gone.errors == 2 and gone.sent == 0


def test_watchdog_usec_rules():
    me = str(os.getpid())
    assert Notifier(env={"WATCHDOG_USEC": "5000000"}).watchdog_usec() == 5_000_000
    assert Notifier(env={"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": me}).watchdog_interval() == 2.5
    # Meant for another process (e.g. inherited by a child): not ours to ping.
    assert Notifier(env={"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}).watchdog_usec() is None
    assert Notifier(env={"WATCHDOG_USEC": "soon"}).watchdog_usec() is None
    assert Notifier(env={"WATCHDOG_USEC": "0"}).watchdog_usec() is None


CHILD = """
import time
from thermod.runtime.sdnotify import Notifier
n = Notifier()
interval = n.watchdog_interval()
n.ready(status=f"started, pinging every {interval} s")
for _ in range(6):
    n.watchdog()
    time.sleep(interval)
n.stopping()
"""


@pytest.mark.slow
def test_service_process_pings_within_its_watchdog(tmp_path):
    """A separate process started the way systemd starts the unit (env vars) keeps the watchdog fed:
    READY first, pings at WATCHDOG_USEC/2, all from the main pid, then STOPPING."""
    path = str(tmp_path / "notify")
    s = _listener(path)
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="400000")
    proc = subprocess.Popen([sys.executable, "-c", CHILD], env=env)
    env["WATCHDOG_PID"] = str(proc.pid)
    msgs = []
    while True:
        lines, pid = _recv(s)
        msgs.append((time.monotonic(), lines, pid))
        if lines == ["STOPPING=1"]:
            break
    assert proc.wait(10) == 0
    # the interval it read from the environment: WATCHDOG_USEC/2 (whether a loaded machine keeps
    # it is the scheduler's business, not something a test can assert)
    assert msgs[0][1] == ["READY=1", "STATUS=started, pinging every 0.2 s"]
    assert {pid for _, _, pid in msgs} == {proc.pid}
    assert [lines for _, lines, _ in msgs[1:]] == [["WATCHDOG=1"]] * 6 + [["STOPPING=1"]]
    s.close()


@pytest.mark.slow
def test_thermod_run_speaks_the_protocol_systemd_expects(tmp_path):
    """`thermod run` (simulated payload) started as systemd would start thermod.service: READY=1 only
    once data flows, WATCHDOG=1 well within WatchdogSec, all from the main pid (NotifyAccess=main),
    STOPPING=1 on SIGTERM."""
    import socket as so
    from pathlib import Path

    with so.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    path = str(tmp_path / "notify")
    lst = _listener(path)
    lst.settimeout(240)  # the first start may render the simulator's loop
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="5000000")  # WatchdogSec=5 in the unit
    env.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[2] / ".numba_cache"))
    exe = Path(sys.executable).with_name("thermod")
    proc = subprocess.Popen([str(exe), "run", "--endpoint", ep, "--seconds", "120"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    msgs = []
    try:
        while True:
            lines, pid = _recv(lst)
            msgs.append((time.monotonic(), lines, pid))
            if "READY=1" in lines:
                t_ready = time.monotonic()
                lst.settimeout(5.0)
            if any(m[1] == ["WATCHDOG=1"] for m in msgs) and time.monotonic() - t_ready > 6.0:
                break
        proc.send_signal(signal.SIGTERM)
        while True:
            lines, pid = _recv(lst)
            msgs.append((time.monotonic(), lines, pid))
            if "STOPPING=1" in lines:
                break
        assert proc.wait(20) == 0, proc.stderr.read()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        lst.close()
    assert {pid for _, _, pid in msgs} == {proc.pid}
    first = [i for i, (_, lines, _) in enumerate(msgs) if "READY=1" in lines][0]
    assert not any("WATCHDOG=1" in lines for _, lines, _ in msgs[:first])  # no pings before ready
    ready_status = [ln for ln in msgs[first][1] if ln.startswith("STATUS=")]
    assert ready_status and "gyro" in ready_status[0]
    pings = [t for t, lines, _ in msgs if lines == ["WATCHDOG=1"]]
    assert len(pings) >= 1
    # the daemon pings about once a second (≤ WatchdogSec/2 = 2.5 s); what it must never do is let
    # WatchdogSec (5 s) pass, which is what the receiver's clock can show even on a loaded machine
    assert max(b - a for a, b in zip([t_ready, *pings], pings, strict=False)) < 5.0
    assert any(ln.startswith("STATUS=") and "fps" in ln for _, lines, _ in msgs for ln in lines)
