"""Which OpenCL device btforge runs on: listing, a build probe, the preference order and the choice.

A device is only chosen once it has built and run a tiny kernel: an OpenCL driver can be installed and list a
device whose compiler cannot target the CPU (PoCL 3.0 with LLVM 14 stops at ``unknown target CPU 'generic'`` on
CPUs newer than its LLVM).  The verdict of each device is kept on disk (``<cache root>/devices``, keyed by
platform, device, driver and pyopencl versions and the probe's source), so only the first process after an
install or upgrade pays the build.

Order: devices matching ``BTFORGE_DEVICE`` / ``--device`` when set (a part of the platform name or version,
device name or driver version, e.g. ``3.1``, ``skylake`` or ``cuda``), else all; among them CPU devices of PoCL
first, newest LLVM (then newest PoCL) first, then other CPU devices, then the rest, each in the order the OpenCL
loader lists them.  The first that builds is chosen; one skipped on the way is named in a warning.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_write_text
from .errors import BtforgeInputError, BtforgeWarning

PREFERENCE = "CPU devices of PoCL first, newest LLVM first"
INSTALL_HINT = ("install Debian's PoCL, whose newer LLVM knows more CPUs (`apt-get install pocl-opencl-icd`, "
                "or run `.ci/setup`)")
_warned: set[str] = set()  # devices already named in a skip warning by this process


def _version_tuple(text: str | None) -> tuple[int, ...]:
    return tuple(int(n) for n in re.findall(r"\d+", text or "")[:3])


class DeviceError(BtforgeInputError):
    """No usable device: about the machine, not the graph node that first needed a device, so it stays as it is
    where the runner would put the node in front of it."""

    def located(self, prefix: str) -> "DeviceError":
        return self


@dataclass
class DeviceEntry:
    """One OpenCL device with what btforge shows and sorts by (PoCL and LLVM versions parsed from the platform)."""

    device: Any
    number: str  # "platform.device", 1-based, in the loader's order
    platform: str
    platform_version: str
    name: str
    version: str
    driver: str
    is_cpu: bool
    pocl: str | None = None
    llvm: str | None = None
    identity: str = ""
    error: str | None = field(default=None, compare=False)  # the probe's verdict once known (None: it builds)

    @property
    def label(self) -> str:
        compiler = ", ".join(x for x in (self.pocl and f"PoCL {self.pocl}", self.llvm and f"LLVM {self.llvm}") if x)
        return f"'{self.name}' ({compiler or self.platform})"

    def matches(self, hint: str) -> bool:
        text = " ".join((self.platform, self.platform_version, self.name, self.driver))
        return hint.lower() in text.lower()

    def sort_key(self) -> tuple:
        newest_first = lambda v: tuple(-n for n in _version_tuple(v))  # noqa: E731
        return (not self.is_cpu, self.pocl is None, newest_first(self.llvm), newest_first(self.pocl))


def device_identity(cl, device) -> str:
    """What a build depends on besides source and options: platform, device, driver and pyopencl versions."""
    return json.dumps([device.platform.name, device.platform.version, device.name, device.version,
                       device.driver_version, cl.VERSION_TEXT])


def _entry(cl, device, number: str) -> DeviceEntry:
    platform_version = device.platform.version.strip()
    pocl = re.search(r"\bPoCL ([^\s,]+)", platform_version)
    llvm = re.search(r"\bLLVM (\d+(?:\.\d+)*)", platform_version)
    return DeviceEntry(device, number, device.platform.name.strip(), platform_version, device.name.strip(),
                       device.version.strip(), device.driver_version.strip(), bool(device.type & cl.device_type.CPU),
                       pocl and pocl.group(1), llvm and llvm.group(1), device_identity(cl, device))


def list_devices(cl) -> list[DeviceEntry]:
    """Every device of every platform, in the loader's order (a platform without devices is left out)."""
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # no ICD registered at all: the loader reports PLATFORM_NOT_FOUND
        return []
    entries = []
    for p_index, platform in enumerate(platforms, 1):
        try:
            devices = platform.get_devices()
        except cl.Error:
            continue
        entries += [_entry(cl, d, f"{p_index}.{d_index}") for d_index, d in enumerate(devices, 1)]
    return entries


def preferred_order(entries: list[DeviceEntry]) -> list[DeviceEntry]:
    return sorted(entries, key=DeviceEntry.sort_key)  # stable: ties keep the loader's order


def first_useful_line(message: str) -> str:
    """The line of a pyopencl error that says what went wrong: the first ``error`` line of the build log, without
    the temporary file's location, else the start of the message."""
    log = message.split("\n\n(options:")[0].split(">:\n", 1)[-1] if ">:\n" in message else ""
    lines = [line.strip() for line in log.splitlines() if line.strip()]
    for line in lines:
        if re.search(r"\berror\b", line, re.IGNORECASE):
            return re.sub(r"\S+\.cl:\d+:\d+: ", "", line)
    if lines:
        return lines[0]
    return message.split(" - ")[0].strip().splitlines()[0] if message.strip() else "unknown OpenCL error"


class BuildProbe:
    """Builds and runs a tiny kernel on a device; remembers each device's verdict in memory and on disk."""

    source = ("kernel void btforge_probe(global float *x)\n"
              "{ size_t i = get_global_id(0); x[i] = fma(x[i], 2.0f, 1.0f); }\n")

    def __init__(self, cl, cache_dir: str | os.PathLike | None = None, recheck: bool = False):
        from .locations import default_cache_root
        self.cl = cl
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_root() / "devices"
        self.recheck = recheck  # ignore verdicts on disk (they are replaced)
        self.builds = 0         # how many probe builds this object ran (tests check the cache)
        self._known: dict[Path, dict] = {}  # verdicts this object has read or found, so each device is probed once

    def source_for(self, entry: DeviceEntry) -> str:
        return self.source

    def verdict(self, entry: DeviceEntry) -> str | None:
        """None if ``entry`` builds and runs the probe, else the reason it does not (also set on ``entry``)."""
        source = self.source_for(entry)
        path = self.cache_dir / (hashlib.blake2b(json.dumps([entry.identity, source]).encode(),
                                                 digest_size=16).hexdigest() + ".json")
        cached = self._known.get(path) or (None if self.recheck else _read_verdict(path, entry.identity))
        if cached is None:
            error, lasting = self._probe(entry, source)
            cached = {"identity": entry.identity, "device": entry.label, "error": error}
            try:
                if lasting:  # not an error that may pass (a device busy or out of resources): probe again then
                    atomic_write_text(path, json.dumps(cached, indent=1))
            except OSError:  # a read-only cache: probe again next time
                pass
        self._known[path] = cached
        entry.error = cached["error"]
        return entry.error

    def _probe(self, entry: DeviceEntry, source: str) -> tuple[str | None, bool]:
        """The probe's error (None if it built and computed the right values), and whether that verdict lasts as
        long as the device's identity (a success, a failed build or wrong values)."""
        cl = self.cl
        self.builds += 1
        values = np.arange(4, dtype=np.float32)
        try:
            context = cl.Context([entry.device])
            program = cl.Program(context, source).build()
            queue = cl.CommandQueue(context)
            buffer = cl.Buffer(context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=values)
            kernel = cl.Kernel(program, "btforge_probe")
            kernel.set_args(buffer)
            cl.enqueue_nd_range_kernel(queue, kernel, values.shape, None)
            cl.enqueue_copy(queue, values, buffer)
            queue.finish()
        except cl.Error as exc:
            return first_useful_line(str(exc)), getattr(exc, "code", None) == cl.status_code.BUILD_PROGRAM_FAILURE
        if values.tolist() != [1.0, 3.0, 5.0, 7.0]:
            return f"the probe kernel computed {values.tolist()} instead of [1.0, 3.0, 5.0, 7.0]", True
        return None, True


def _read_verdict(path: Path, identity: str) -> dict | None:
    try:
        cached = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(cached, dict) and cached.get("identity") == identity and "error" in cached
    return cached if ok and (cached["error"] is None or isinstance(cached["error"], str)) else None


@dataclass
class Choice:
    """The chosen device, why, and the devices tried before it that did not build (with their errors)."""

    entry: DeviceEntry
    reason: str
    skipped: list[DeviceEntry]


def hint_and_source(hint: str | None) -> tuple[str | None, str]:
    if hint is not None:
        return hint or None, "--device"
    return os.environ.get("BTFORGE_DEVICE") or None, "BTFORGE_DEVICE"


def choose_device(cl, hint: str | None = None, probe: BuildProbe | None = None,
                  entries: list[DeviceEntry] | None = None, warn: bool = True) -> Choice:
    """The first device that builds among those ``hint`` (else ``BTFORGE_DEVICE``) selects, in btforge's order.

    Each device skipped is named in one :class:`BtforgeWarning` per process (``warn``); if none builds, one
    :class:`BtforgeInputError` lists every device tried with its error and the fix."""
    entries = list_devices(cl) if entries is None else entries
    if not entries:
        raise DeviceError("OpenCL", "expected at least one OpenCL device, found none",
                                f"{INSTALL_HINT}, or `pip install pocl-binary-distribution`")
    hint, source = hint_and_source(hint)
    candidates = preferred_order(matching_devices(entries, hint, source))
    probe = probe or BuildProbe(cl)
    for position, entry in enumerate(candidates):
        if probe.verdict(entry) is None:
            choice = Choice(entry, _reason(hint, source, position), candidates[:position])
            if warn:
                _warn_skipped(choice)
            return choice
    raise _nothing_builds(candidates, len(entries), hint, source)


def matching_devices(entries: list[DeviceEntry], hint: str | None, source: str) -> list[DeviceEntry]:
    if not hint or not entries:
        return entries
    matching = [e for e in entries if e.matches(hint)]
    if not matching:
        names = ", ".join(e.label for e in entries)
        raise DeviceError("device", f"no OpenCL device matches {source}={hint!r}; found {names}",
                                f"set {source} to part of a platform name or version, device name or driver "
                                "version (`btforge devices` lists them)")
    return matching


def _reason(hint: str | None, source: str, skipped: int) -> str:
    before = f"; {skipped} device(s) before it do not build" if skipped else ""
    if hint:
        return f"{source}={hint!r} selects it and it builds{before}"
    return f"the first device that builds, in btforge's order ({PREFERENCE}){before}"


def _warn_skipped(choice: Choice) -> None:
    for entry in choice.skipped:
        if entry.identity + entry.number in _warned:
            continue
        _warned.add(entry.identity + entry.number)
        warnings.warn(f"OpenCL device {entry.label} cannot build kernels ({entry.error}); using "
                      f"{choice.entry.label} instead (`btforge devices` shows every device)", BtforgeWarning,
                      stacklevel=4)


def _nothing_builds(tried: list[DeviceEntry], found: int, hint: str | None, source: str) -> DeviceError:
    lines = "".join(f"\n    {e.number} {e.label}: {e.error}" for e in tried)
    fix = (f"{INSTALL_HINT}; `btforge devices` then shows which device builds, and BTFORGE_DEVICE (or --device) "
           "picks one by part of its name or version")
    if hint and found > len(tried):
        fix = (f"{source}={hint!r} selects only these: unset it or choose another of the {found} devices "
               f"(`btforge devices` lists them), or {INSTALL_HINT}")
    elif hint:
        fix = f"{INSTALL_HINT}, and unset {source} or set it to the new device"
    return DeviceError("OpenCL devices", f"expected a device that builds OpenCL kernels, found none that "
                             f"does ({len(tried)} tried):{lines}", fix)


def describe_devices(cl, hint: str | None = None, probe: BuildProbe | None = None) -> dict:
    """Every device with its versions, compiler and probe verdict, which is chosen and why (``btforge devices``)."""
    entries = list_devices(cl)
    probe = probe or BuildProbe(cl)
    for entry in entries:
        probe.verdict(entry)
    try:
        choice = choose_device(cl, hint, probe, entries, warn=False)
        chosen, reason = choice.entry.number, choice.reason
    except BtforgeInputError as exc:
        chosen, reason = None, exc.render()
    records = [{k: v for k, v in vars(e).items() if k not in ("device", "identity")} | {"builds": e.error is None}
               for e in entries]
    return {"devices": records, "chosen": chosen, "reason": reason, "preference": PREFERENCE,
            "verdicts": str(probe.cache_dir)}


def format_devices(description: dict) -> str:
    """``describe_devices`` as text: each platform, its devices, whether each builds, and the choice."""
    out, platform = [], None
    for d in description["devices"]:
        if d["number"].split(".")[0] != platform:
            platform = d["number"].split(".")[0]
            compiler = ", ".join(x for x in (d["pocl"] and f"PoCL {d['pocl']}", d["llvm"] and f"LLVM {d['llvm']}") if x)
            out += [f"platform {platform}: {d['platform']}", f"    version   {d['platform_version']}",
                    f"    compiler  {compiler or 'not PoCL: the driver does not say'}"]
        mark = "   <- chosen" if d["number"] == description["chosen"] else ""
        out += [f"  device {d['number']}: {d['name']}{mark}",
                f"    type      {'CPU' if d['is_cpu'] else 'not a CPU'}, {d['version']}, driver {d['driver']}",
                f"    builds    {'yes' if d['builds'] else 'no: ' + d['error']}"]
    if description["chosen"]:
        out.append(f"chosen: device {description['chosen']}, {description['reason']}")
    else:
        out.append(f"chosen: none. {description['reason']}")
    out.append(f"(probe verdicts are kept in {description['verdicts']}; `btforge devices --recheck` probes again)")
    return "\n".join(out)
