"""`thermod run|watch|record|import|deblur|export|sim|discrepancy|bench`.

Each command lives in its own module exposing `add_arguments(parser)` and `run(args) -> int`;
only the chosen module is imported, so `thermod watch` does not pay for numba start-up.

Exit status: 0 success; 2 bad input, configuration, device or usage (a ThermodError: one line
naming the file, key or device); 1 an unexpected internal error (one line naming the command;
`-v` adds the traceback); 130 interrupted. No traceback reaches the user without `-v`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback

from thermod.errors import ThermodError

COMMANDS = {
    "run": ("thermod.cli.run", "run the acquisition and deblurring daemon (default: simulated payload)"),
    "watch": ("thermod.cli.watch", "subscribe to a running daemon: rates, latency, drops, previews"),
    "record": ("thermod.cli.record", "subscribe to raw frames and gyro samples and write a recording"),
    "import": ("thermod.cli.import_", "ROS bag, or thermal video + flight log (--gyro) → format v1"),
    "deblur": ("thermod.cli.deblur", "deblur recordings offline"),
    "export": ("thermod.cli.export", "write a recording's synced gyro for Gyroflow (.gcsv)"),
    "sim": ("thermod.cli.sim", "simulate a recording with known truth"),
    "discrepancy": ("thermod.cli.discrepancy", "compare simulation with a recording and fix the model"),
    "bench": ("thermod.cli.bench", "run the benchmark suites and print their tables"),
}


def _usage() -> str:
    lines = ["usage: thermod COMMAND [options]", "", "commands:"]
    lines += [f"  {name:<12} {helptext}" for name, (_, helptext) in COMMANDS.items()]
    lines += ["", "`thermod COMMAND --help` for a command's options.",
              "exit status: 0 ok, 2 bad input/configuration/device, 1 internal error (-v: traceback)"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    if argv[0] == "--version":
        from thermod import __version__
        print(f"thermod {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"thermod: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, helptext = COMMANDS[name]
    try:
        module = importlib.import_module(module_name)   # seconds for the numerical commands
    except KeyboardInterrupt:                            # Ctrl-C meanwhile: as during the command
        return 130
    parser = argparse.ArgumentParser(prog=f"thermod {name}", description=helptext)
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    module.add_arguments(parser)
    args = parser.parse_args(rest)
    logging.basicConfig(level=logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose else
                        logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return int(module.run(args) or 0)
    except ThermodError as e:          # several problems (a configuration's): one prefixed line each
        for line in str(e).splitlines() or [""]:
            print(f"thermod {name}: error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # noqa: BLE001 - a bug gets one line, not a traceback (unless -v)
        if args.verbose:
            traceback.print_exc()
        hint = "" if args.verbose else " (run with -v for the traceback)"
        print(f"thermod {name}: internal error: {type(e).__name__}: {e}{hint}", file=sys.stderr)
        return 1

