"""systemd integration: the unit passes `systemd-analyze verify` and the offline security audit,
sysusers/tmpfiles configs apply to a scratch root, and the udev rules give each sensor the right
group, mode and stable name. (The notify/watchdog protocol itself: tests/runtime/test_sdnotify.py.)"""

import fnmatch
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parents[2] / "systemd"
UNIT = SYSTEMD / "thermod.service"


def unit_settings(path=UNIT) -> dict[str, list[str]]:
    """{"Section.Key": [values in order]}; repeated keys (DeviceAllow=, Environment=) accumulate."""
    out, section, text = {}, None, path.read_text().replace("\\\n", " ")
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.setdefault(f"{section}.{key.strip()}", []).append(value.strip())
    return out


def _verify(require, path: Path) -> tuple[int, list[str]]:
    exe = shutil.which("systemd-analyze")
    require(exe is not None, "systemd-analyze (Debian package systemd)")
    r = subprocess.run([exe, "verify", "--man=no", str(path)], capture_output=True, text=True, timeout=60)
    ours = [ln for ln in (r.stdout + r.stderr).splitlines() if path.name in ln or str(path) in ln]
    return r.returncode, ours


def test_unit_passes_systemd_analyze_verify(require, tmp_path):
    unit = tmp_path / "thermod.service"
    shutil.copy(UNIT, unit)
    rc, complaints = _verify(require, unit)
    assert rc == 0 and complaints == []
    # The check has teeth: a misspelt key and a bad value are reported.
    broken = tmp_path / "broken" / "thermod.service"
    broken.parent.mkdir()
    broken.write_text(UNIT.read_text().replace("Type=notify", "Tpye=notify").replace("WatchdogSec=5",
                                                                                     "WatchdogSec=soon"))
    rc, complaints = _verify(require, broken)
    assert any("Tpye" in c for c in complaints) and any("soon" in c for c in complaints)


def test_unit_security_exposure_is_low(require):
    exe = shutil.which("systemd-analyze")
    require(exe is not None, "systemd-analyze (Debian package systemd)")
    r = subprocess.run([exe, "security", "--offline=yes", "--no-pager", str(UNIT)], capture_output=True,
                       text=True, timeout=60)
    m = re.search(r"Overall exposure level for thermod\.service: ([0-9.]+)", r.stdout + r.stderr)
    assert m, r.stdout + r.stderr
    assert float(m.group(1)) <= 3.0  # "OK" band; hardware access and the network keep it above ~2


def test_unit_contract():
    s = unit_settings()
    one = {k: v[-1] for k, v in s.items()}
    assert one["Service.Type"] == "notify" and one["Service.NotifyAccess"] == "main"
    assert 2 <= float(one["Service.WatchdogSec"]) <= 30 and one["Service.Restart"] == "on-failure"
    assert one["Service.User"] == "thermod" and one["Install.WantedBy"] == "multi-user.target"
    argv = shlex.split(one["Service.ExecStart"])
    assert argv[:3] == ["/usr/bin/env", "thermod", "run"]
    assert argv[argv.index("--config") + 1].startswith("/etc/")
    # numba: a JIT needs W+X pages and a writable cache directory.
    assert "Service.MemoryDenyWriteExecute" not in s
    assert one["Service.CacheDirectory"] == "thermod"
    assert "NUMBA_CACHE_DIR=%C/thermod/numba" in s["Service.Environment"]
    # /etc/thermod is root:thermod from tmpfiles; ConfigurationDirectory= would make it root:root 0750
    assert "Service.ConfigurationDirectory" not in s and "Service.SupplementaryGroups" not in s
    # Real-time priority per sensor thread: a limit for the process, not a policy.
    assert int(one["Service.LimitRTPRIO"]) >= 20
    assert "Service.CPUSchedulingPolicy" not in s and "Service.RestrictRealtime" not in s
    # Least privilege.
    assert one["Service.CapabilityBoundingSet"] == "" and one["Service.NoNewPrivileges"] == "yes"
    assert one["Service.ProtectSystem"] == "strict" and one["Service.ProtectHome"] == "yes"
    assert one["Service.PrivateTmp"] == "yes" and s["Service.SystemCallFilter"][0] == "@system-service"
    families = set(one["Service.RestrictAddressFamilies"].split())
    assert families == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}
    # Devices by class (major names from /proc/devices), so replugged devices keep working.
    assert one["Service.DevicePolicy"] == "closed"
    allow = dict(v.split() for v in s["Service.DeviceAllow"])
    assert all(re.fullmatch(r"char-[A-Za-z0-9_]+", k) and set(v) <= set("rwm") for k, v in allow.items())
    for cls in ("char-i2c", "char-spi", "char-iio", "char-ttyUSB", "char-ttyACM", "char-video4linux"):
        assert allow.get(cls) == "rw", cls


def test_sysusers_and_tmpfiles_apply_to_a_scratch_root(require, tmp_path):
    sysusers, tmpfiles = shutil.which("systemd-sysusers"), shutil.which("systemd-tmpfiles")
    require(sysusers is not None and tmpfiles is not None, "systemd-sysusers/systemd-tmpfiles")
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    (root / "etc" / "passwd").write_text("root:x:0:0::/root:/bin/sh\n")
    (root / "etc" / "group").write_text("root:x:0:\ndialout:x:20:\nvideo:x:44:\nplugdev:x:46:\n")
    r = subprocess.run([sysusers, f"--root={root}", str(SYSTEMD / "thermod.sysusers.conf")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    users = {ln.split(":")[0]: ln.split(":") for ln in (root / "etc/passwd").read_text().splitlines()}
    groups = {ln.split(":")[0]: ln.split(":") for ln in (root / "etc/group").read_text().splitlines()}
    uid, gid, home = int(users["thermod"][2]), int(users["thermod"][3]), users["thermod"][5]
    assert 0 < uid < 1000 and home == "/var/lib/thermod" and users["thermod"][6].endswith("nologin")
    member_of = {g for g, f in groups.items() if "thermod" in f[3].split(",")}
    assert member_of == {"i2c", "spi", "dialout", "video"}   # the device groups it opens, nothing more
    assert groups["dialout"][2] == "20"  # existing groups are reused, not recreated
    # an installed configuration with a too-open mode is brought to 0640 root:thermod
    (root / "etc/thermod").mkdir()
    conf = root / "etc/thermod/thermod.toml"
    conf.write_text("[sources.gyro]\nkind = 'sim'\n")
    conf.chmod(0o666)
    r = subprocess.run([tmpfiles, f"--root={root}", "--create", str(SYSTEMD / "thermod.tmpfiles.conf")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    etc, cache = (root / "etc/thermod").stat(), (root / "var/cache/thermod/numba").stat()
    assert (etc.st_uid, etc.st_gid, etc.st_mode & 0o777) == (0, gid, 0o750)
    assert (cache.st_uid, cache.st_gid, cache.st_mode & 0o777) == (uid, gid, 0o750)
    c = conf.stat()
    assert (c.st_uid, c.st_gid, c.st_mode & 0o777) == (0, gid, 0o640)


# ------------------------------------------------------------------------------------ udev rules
RULE_KEY = re.compile(r'\s*([A-Z_]+)(\{[^}]*\})?\s*(==|!=|\+=|-=|:=|=)\s*"((?:[^"\\]|\\.)*)"\s*(,|$)')
MATCH_KEYS = {"ACTION", "DEVPATH", "KERNEL", "KERNELS", "NAME", "SYMLINK", "SUBSYSTEM", "SUBSYSTEMS",
              "DRIVER", "DRIVERS", "ATTR", "ATTRS", "SYSCTL", "TAG", "TAGS", "ENV", "CONST", "TEST",
              "PROGRAM", "RESULT"}
ASSIGN_KEYS = {"NAME", "SYMLINK", "OWNER", "GROUP", "MODE", "SECLABEL", "ATTR", "SYSCTL", "ENV", "TAG", "RUN",
               "LABEL", "GOTO", "IMPORT", "OPTIONS"}


def parse_rules(path: Path) -> list[list[tuple[str, str | None, str, str]]]:
    """udev(7) syntax: one rule per logical line (backslash continues), comma-separated
    KEY[{attr}] OP "value"; match keys take ==/!=, assignment keys =, +=, -=, :=."""
    rules = []
    for n, line in enumerate(path.read_text().replace("\\\n", " ").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        pos, rule = 0, []
        while pos < len(line):
            m = RULE_KEY.match(line, pos)
            assert m, f"{path.name} rule {n}: cannot parse at {line[pos:pos + 40]!r}"
            key, attr, op, value = m.group(1), m.group(2), m.group(3), m.group(4)
            if op in ("==", "!="):
                assert key in MATCH_KEYS, f"{path.name} rule {n}: {key} is not a match key"
            else:
                assert key in ASSIGN_KEYS, f"{path.name} rule {n}: {key} cannot be assigned"
            if key in ("ATTR", "ATTRS", "ENV"):
                assert attr, f"{path.name} rule {n}: {key} needs {{name}}"
            rule.append((key, attr and attr[1:-1], op, value))
            pos = m.end()
        rules.append(rule)
    return rules


def apply_rules(rules, device: dict) -> dict:
    """Evaluate the rules for one device: match keys against `device` (ATTRS/DRIVERS also see the
    parents' values, flattened into it), glob patterns with `|` alternatives; collect assignments."""
    result = {"SYMLINK": [], "RUN": [], "TAG": [], "ATTR": {}}
    for rule in rules:
        ok = True
        for key, attr, op, value in rule:
            if op not in ("==", "!="):
                continue
            have = device.get(f"{key}{{{attr}}}" if attr else key)
            hit = have is not None and any(fnmatch.fnmatchcase(have, p) for p in value.split("|"))
            ok &= hit if op == "==" else not hit
        if not ok:
            continue
        for key, attr, op, value in rule:
            if op in ("==", "!="):
                continue
            if key in ("SYMLINK", "RUN", "TAG"):
                result[key].append(value)
            elif key == "ATTR":
                result["ATTR"][attr] = value
            else:
                result[key] = value
    return result


RULES = parse_rules(SYSTEMD / "99-thermod.rules")


@pytest.mark.parametrize("device, group, symlink", [
    ({"ACTION": "add", "SUBSYSTEM": "i2c-dev", "KERNEL": "i2c-1"}, "i2c", None),
    ({"ACTION": "add", "SUBSYSTEM": "spidev", "KERNEL": "spidev0.0"}, "spi", None),
    ({"ACTION": "add", "SUBSYSTEM": "iio", "KERNEL": "iio:device0", "ATTR{name}": "icm42688-gyro"},
     "thermod", "thermod/iio-gyro"),
    ({"ACTION": "add", "SUBSYSTEM": "iio", "KERNEL": "iio:device1", "ATTR{name}": "ads1015"},
     "thermod", None),
    ({"ACTION": "add", "SUBSYSTEM": "tty", "KERNEL": "ttyUSB0", "ATTRS{idVendor}": "0403"},
     "dialout", "thermod/imu-serial"),
    ({"ACTION": "add", "SUBSYSTEM": "video4linux", "KERNEL": "video0", "ATTRS{idVendor}": "09cb",
      "ATTR{index}": "0"}, "video", "thermod/camera"),
    ({"ACTION": "add", "SUBSYSTEM": "video4linux", "KERNEL": "video1", "ATTRS{idVendor}": "09cb",
      "ATTR{index}": "1"}, None, None),  # the Boson's metadata node is not the camera
    ({"ACTION": "add", "SUBSYSTEM": "tty", "KERNEL": "ttyACM0", "ATTRS{idVendor}": "09cb"},
     "dialout", "thermod/boson-serial"),
    ({"ACTION": "add", "SUBSYSTEM": "video4linux", "KERNEL": "video2", "ATTRS{idVendor}": "1e4e",
      "ATTRS{idProduct}": "0100", "ATTR{index}": "0"}, "video", "thermod/camera"),
    ({"ACTION": "add", "SUBSYSTEM": "usb", "ENV{DEVTYPE}": "usb_device", "ATTR{idVendor}": "09cb"},
     "plugdev", None),
    ({"ACTION": "add", "SUBSYSTEM": "tty", "KERNEL": "ttyUSB1", "ATTRS{idVendor}": "067b"}, None, None),
    ({"ACTION": "add", "SUBSYSTEM": "input", "KERNEL": "event3"}, None, None),
])
def test_udev_rules(device, group, symlink):
    r = apply_rules(RULES, device)
    assert r.get("GROUP") == group
    assert r.get("MODE") == ("0660" if group else None)
    assert r["SYMLINK"] == ([symlink] if symlink else [])


def test_udev_ftdi_low_latency_and_iio_sysfs_access():
    r = apply_rules(RULES, {"ACTION": "add", "SUBSYSTEM": "usb-serial", "DRIVER": "ftdi_sio",
                            "KERNEL": "ttyUSB0"})
    assert r["ATTR"] == {"latency_timer": "1"}
    r = apply_rules(RULES, {"ACTION": "add", "SUBSYSTEM": "iio", "KERNEL": "iio:device0"})
    (cmd,) = r["RUN"]
    for what in ("buffer", "scan_elements", "current_timestamp_clock", "chgrp -R thermod", "chmod -R g+w"):
        assert what in cmd
    assert apply_rules(RULES, {"ACTION": "remove", "SUBSYSTEM": "iio", "KERNEL": "iio:device0"})["RUN"] == []


def test_udev_parser_rejects_mistakes(tmp_path):
    bad = tmp_path / "bad.rules"
    for text, msg in [('SUBSYSTEM="tty", GROUP="dialout"', "SUBSYSTEM cannot be assigned"),
                      ('KERNEL=="tty*", GROUP=="dialout"', "GROUP is not a match key"),
                      ('KERNEL=="tty*" GROUP="dialout"', "cannot parse"),
                      ('ATTRS=="0403", GROUP="dialout"', "needs {name}")]:
        bad.write_text(text + "\n")
        with pytest.raises(AssertionError, match=re.escape(msg)):
            parse_rules(bad)


def test_execstart_is_a_valid_thermod_command_line():
    """The unit's ExecStart arguments parse with the real `thermod run` parser."""
    import argparse

    from thermod import cli
    from thermod.cli import run

    argv = shlex.split(unit_settings()["Service.ExecStart"][-1])
    assert argv[1] == "thermod" and argv[2] in cli.COMMANDS and cli.COMMANDS[argv[2]][0] == "thermod.cli.run"
    parser = argparse.ArgumentParser(prog="thermod run")
    run.add_arguments(parser)
    args = parser.parse_args(argv[3:])
    assert args.config == "/etc/thermod/thermod.toml"
