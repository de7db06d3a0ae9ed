"""`thermod run`: the daemon (default: the simulated payload of the packaged sim.toml).

SIGTERM/SIGINT stop it cleanly; SIGHUP reloads calibration and deblur settings (see
`thermod.runtime.daemon`).
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import stat
import threading

log = logging.getLogger("thermod.runtime.daemon")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", metavar="FILE", help="TOML configuration (default: the packaged "
                        "sim.toml, the simulated payload)")
    parser.add_argument("--endpoint", metavar="EP", help="override publish.endpoint, e.g. tcp://127.0.0.1:5600")
    parser.add_argument("--raw", action="store_true", help="also publish raw frames (publish.raw = true)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override any configuration key, e.g. --set deblur.method=wiener (repeatable)")
    parser.add_argument("--rtsp", metavar="URL", help="serve the live view as H.264 over RTSP, e.g. "
                        "rtsp://127.0.0.1:8554/thermal (rtsp.enabled = true, rtsp.url = URL)")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--list-keys", action="store_true", help="print every configuration key with its "
                        "default, meaning and allowed values (a TOML reference), and exit")


def _overrides(args) -> tuple[dict, dict]:
    """({dotted key: value}, {dotted key: the option that set it}) from the command line."""
    from thermod.runtime import config

    ov = dict(config.parse_override(s) for s in args.overrides)
    origins = {}
    if args.endpoint:
        ov["publish.endpoint"], origins["publish.endpoint"] = args.endpoint, f"--endpoint {args.endpoint}"
    if args.raw:
        ov["publish.raw"], origins["publish.raw"] = True, "--raw"
    if args.rtsp:
        ov["rtsp.enabled"], origins["rtsp.enabled"] = True, "--rtsp"
        ov["rtsp.url"], origins["rtsp.url"] = args.rtsp, f"--rtsp {args.rtsp}"
    return ov, origins


def _warn_if_open(path: str) -> None:
    """The configuration names devices, endpoints and key files: root's to edit, the daemon's to read."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return
    if mode & (stat.S_IWGRP | stat.S_IWOTH | stat.S_IROTH):
        log.warning("%s: mode %03o lets others read or change it; install it 0640 root:thermod "
                    "(systemd/thermod.tmpfiles.conf does)", path, stat.S_IMODE(mode))


def _set_from_handler(event: threading.Event) -> None:
    """`event.set()` on behalf of a signal handler, by a thread of its own: a handler runs in the main
    thread between any two bytecodes, possibly while that thread holds the event's lock (inside its
    ``wait``, which `Daemon.serve` calls 20 times a second), where a direct ``set`` deadlocks."""
    threading.Thread(target=event.set, name="thermod-signal", daemon=True).start()


def signal_handlers(stop: threading.Event, reload_req: threading.Event):
    """(on_term, on_hup): SIGTERM and SIGINT set `stop`, SIGHUP sets `reload_req`."""

    def on_term(signum, frame):
        log.info("%s: shutting down", signal.Signals(signum).name)
        _set_from_handler(stop)

    def on_hup(signum, frame):
        _set_from_handler(reload_req)

    return on_term, on_hup


def run(args) -> int:
    stop = threading.Event()
    reload_req = threading.Event()
    on_term, on_hup = signal_handlers(stop, reload_req)
    # first, before the daemon's and the schema's modules are imported (seconds on a loaded payload):
    # a stop during the start ends it there, and a SIGHUP then (a reload) waits for the daemon to serve
    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    signal.signal(signal.SIGHUP, on_hup)
    from thermod.runtime import config  # the configuration's schema imports the physics (~1 s)

    if args.list_keys:
        print(config.reference(), end="")
        return 0
    ov, origins = _overrides(args)
    cfg = config.load(args.config, ov, origins=origins)
    logging.getLogger("thermod").setLevel(cfg.logging.level.upper())
    if not logging.getLogger().handlers:
        logging.basicConfig(format="%(levelname)s %(name)s: %(message)s")
    if args.config:
        _warn_if_open(args.config)
    from thermod.runtime.daemon import Daemon

    d = Daemon(cfg, overrides=ov)
    try:
        started = d.start(abort=stop)
        # Start-up (numba, LLVM, the loaded modules) leaves ~10⁵ objects that live as long as the process:
        # frozen, the collector no longer walks them, neither in full collections while frames flow nor
        # in the interpreter's teardown, which otherwise spends most of the 2 s a stop is allowed (also
        # after a start that a stop abandoned)
        gc.freeze()
        if started:
            d.serve(stop, reload_req, seconds=args.seconds)
    finally:
        d.stop()
    return 0
