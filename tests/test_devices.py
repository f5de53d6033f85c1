"""Choosing the OpenCL device: the build probe, its verdicts on disk, the fallback past a device that cannot build,
the one warning, the all-fail error, BTFORGE_DEVICE / --device, and ``btforge devices``.

A device that cannot build is simulated by giving the probe a kernel whose build fails in the compiler with the
message of the real failure (PoCL 3.0 on a CPU newer than its LLVM); everything else is the real code on the
machine's real devices.
"""
import dataclasses
import json
import warnings

import numpy as np
import pyopencl as cl
import pytest
from PIL import Image

from btforge import backend, devices
from btforge.cli import main
from btforge.devices import BuildProbe, DeviceEntry, choose_device, list_devices, preferred_order
from btforge.errors import BtforgeInputError, BtforgeWarning

BROKEN = "#error unknown target CPU 'generic'\nkernel void btforge_probe(global float *x) { }\n"


class FailingOn(BuildProbe):
    """The real probe, except that devices numbered in ``failing`` get a kernel their compiler rejects."""

    def __init__(self, cl_module, cache_dir, failing):
        super().__init__(cl_module, cache_dir)
        self.failing = set(failing)

    def source_for(self, entry):
        return BROKEN if entry.number in self.failing else self.source


@pytest.fixture
def entries(tmp_path_factory):
    """The machine's devices that build, in btforge's order; a single one is listed twice, so that a fallback is
    possible."""
    probe = BuildProbe(cl, tmp_path_factory.mktemp("verdicts"))
    found = [e for e in preferred_order(list_devices(cl)) if probe.verdict(e) is None]
    if not found:
        pytest.skip("no OpenCL device builds")
    if len(found) == 1:
        found.append(dataclasses.replace(found[0], number="copy"))
    return found


@pytest.fixture(autouse=True)
def fresh_process_state(monkeypatch):
    """Each test sees a process that has warned about nothing yet and has no backend."""
    monkeypatch.setattr(devices, "_warned", set())
    monkeypatch.setattr(backend, "_backend", None)
    monkeypatch.setattr(backend, "_device_hint", None)
    monkeypatch.delenv("BTFORGE_DEVICE", raising=False)


def test_probe_verdict_is_kept_on_disk_and_reused(tmp_path, entries):
    first = BuildProbe(cl, tmp_path)
    assert first.verdict(entries[0]) is None and first.builds == 1
    (kept,) = tmp_path.glob("*.json")
    assert json.loads(kept.read_text()) == {"identity": entries[0].identity, "device": entries[0].label,
                                            "error": None}
    again = BuildProbe(cl, tmp_path)
    assert again.verdict(entries[0]) is None and again.builds == 0   # a warm process pays no build
    kept.write_text("{not json")                                     # a damaged verdict is probed again
    damaged = BuildProbe(cl, tmp_path)
    assert damaged.verdict(entries[0]) is None and damaged.builds == 1
    assert json.loads(kept.read_text())["error"] is None


def test_recheck_probes_every_device_once(tmp_path):
    BuildProbe(cl, tmp_path).verdict(list_devices(cl)[0])
    probe = BuildProbe(cl, tmp_path, recheck=True)
    described = devices.describe_devices(cl, probe=probe)
    assert probe.builds == len(list_devices(cl)) == len(described["devices"])


def test_a_failing_verdict_is_kept_with_its_first_error_line(tmp_path, entries):
    probe = FailingOn(cl, tmp_path, {entries[0].number})
    error = probe.verdict(entries[0])
    assert error == "error: unknown target CPU 'generic'"           # the log's error line, without the temp file
    assert FailingOn(cl, tmp_path, {entries[0].number}).verdict(entries[0]) == error
    assert BuildProbe(cl, tmp_path).verdict(entries[0]) is None      # the verdict is per probe source too


def test_falls_back_past_a_device_that_cannot_build_and_warns_once(tmp_path, entries):
    probe = FailingOn(cl, tmp_path, {entries[0].number})
    with pytest.warns(BtforgeWarning) as caught:
        choice = choose_device(cl, probe=probe, entries=entries)
    assert choice.entry is entries[1] and choice.skipped == [entries[0]]
    assert "1 device(s) before it do not build" in choice.reason
    (warning,) = [str(w.message) for w in caught]
    assert entries[0].label in warning and "unknown target CPU 'generic'" in warning and entries[1].label in warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")                                 # the same process does not warn again
        assert choose_device(cl, probe=probe, entries=entries).entry is entries[1]


def test_no_device_builds_is_one_error_listing_every_device(tmp_path, entries):
    probe = FailingOn(cl, tmp_path, {e.number for e in entries})
    with pytest.raises(BtforgeInputError) as raised:
        choose_device(cl, probe=probe, entries=entries)
    message = raised.value.render()
    for entry in entries:
        assert f"{entry.number} {entry.label}: error: unknown target CPU 'generic'" in message
    assert f"({len(entries)} tried)" in message and "apt-get install pocl-opencl-icd" in message


def unique_hint(entry, entries):
    """A part of ``entry``'s names or versions that no other listed device has (None if there is none)."""
    others = [e for e in entries if e.number != entry.number]
    return next((h for h in (entry.driver, entry.name, entry.platform_version)
                 if entry.matches(h) and not any(e.matches(h) for e in others)), None)


def test_device_hint_selects_among_matching_devices(tmp_path, entries, monkeypatch):
    probe = BuildProbe(cl, tmp_path)
    last, first = entries[-1], entries[0]
    if unique_hint(last, entries):  # two real devices: BTFORGE_DEVICE picks the one btforge would not
        monkeypatch.setenv("BTFORGE_DEVICE", unique_hint(last, entries))
        choice = choose_device(cl, probe=probe, entries=entries)
        assert choice.entry is last and choice.reason.startswith("BTFORGE_DEVICE=")
    hint = first.name
    choice = choose_device(cl, hint=hint, probe=probe, entries=entries)   # --device wins over the env
    assert choice.entry is first and choice.reason == f"--device={hint!r} selects it and it builds"
    with pytest.raises(BtforgeInputError, match="no OpenCL device matches --device='no such device'"):
        choose_device(cl, hint="no such device", probe=probe, entries=entries)


def test_a_hint_whose_devices_cannot_build_says_so(tmp_path, entries):
    hint = unique_hint(entries[-1], entries)
    if not hint:
        pytest.skip("needs two real devices told apart by name or version")
    probe = FailingOn(cl, tmp_path, {entries[-1].number})
    with pytest.raises(BtforgeInputError) as raised:
        choose_device(cl, hint=hint, probe=probe, entries=entries)
    assert entries[-1].label in str(raised.value) and "selects only these" in str(raised.value)


def test_preference_cpu_pocl_newest_llvm_first():
    def entry(number, cpu=True, pocl="3.1", llvm="15.0.6"):
        return DeviceEntry(None, number, "p", "v", "d", "v", "1", cpu, pocl, llvm)
    listed = [entry("1.1", cpu=False), entry("2.1", pocl=None, llvm=None), entry("3.1", pocl="3.0-rc2", llvm="14.0.6"),
              entry("4.1", pocl="5.0", llvm="17.0.1"), entry("5.1")]
    assert [e.number for e in preferred_order(listed)] == ["4.1", "5.1", "3.1", "2.1", "1.1"]


def test_first_useful_line_of_pyopencl_errors():
    message = ("clBuildProgram failed: BUILD_PROGRAM_FAILURE - clBuildProgram failed: BUILD_PROGRAM_FAILURE\n\n"
               "Build on <pyopencl.Device 'pthread-AMD EPYC' on 'Portable Computing Language' at 0x1>:\n\n"
               "warning: something harmless\nerror: unknown target CPU 'generic'\nnote: valid target CPU values "
               "are: nocona, core2\n\n(options: -I /x/pyopencl/cl)")
    assert devices.first_useful_line(message) == "error: unknown target CPU 'generic'"
    assert devices.first_useful_line("clCreateContext failed: DEVICE_NOT_AVAILABLE - clCreateContext failed: "
                                     "DEVICE_NOT_AVAILABLE") == "clCreateContext failed: DEVICE_NOT_AVAILABLE"


def test_btforge_devices_lists_every_device_and_the_choice(capsys, entries):
    assert main(["devices"]) == 0
    text = capsys.readouterr().out
    for entry in list_devices(cl):
        assert f"device {entry.number}: {entry.name}" in text and entry.platform_version in text
    assert text.count("<- chosen") == 1 and "builds    yes" in text
    assert "the first device that builds, in btforge's order" in text
    assert main(["devices", "--json"]) == 0
    described = json.loads(capsys.readouterr().out)
    assert described["chosen"] == entries[0].number and len(described["devices"]) == len(list_devices(cl))
    building = {e.number for e in entries}
    assert all(d["builds"] == (d["error"] is None) == (d["number"] in building) for d in described["devices"])
    if entries[0].pocl:
        assert described["devices"][[d["number"] for d in described["devices"]].index(entries[0].number)]["llvm"]


def test_btforge_devices_shows_a_device_that_cannot_build(capsys, entries, monkeypatch):
    failing = entries[0].number
    monkeypatch.setattr(BuildProbe, "source_for", lambda self, e: BROKEN if e.number == failing else self.source)
    assert main(["devices"]) == 0
    text = capsys.readouterr().out
    assert "builds    no: error: unknown target CPU 'generic'" in text
    assert text.count("<- chosen") == (1 if entries[1].number != "copy" else 0)


def tiny_capture_graph(tmp_path):
    (tmp_path / "cap").mkdir()
    rows = []
    for i in range(6):
        Image.fromarray(np.full((8, 8, 3), 40 + 30 * i, np.uint8)).save(tmp_path / "cap" / f"l{i}.png")
        rows.append(f"l{i}.png {0.3 * np.cos(i):.3f} {0.3 * np.sin(i):.3f} 0.9")
    (tmp_path / "cap" / "dirs.lp").write_text("6\n" + "\n".join(rows) + "\n")
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: {tmp_path / 'cap' / 'dirs.lp'}}}}}\n"
                     "  fit: {stage: ptm.fit, inputs: {stack: read.stack}}\n")
    return ["run", str(graph), "--out", str(tmp_path / "out"), "--no-cache", "--report", str(tmp_path / "r.json")]


def test_run_warns_on_the_cli_and_in_the_report(tmp_path, capsys, entries, monkeypatch):
    if entries[1].number == "copy":
        pytest.skip("needs two real devices")
    failing = entries[0].number
    monkeypatch.setattr(BuildProbe, "source_for", lambda self, e: BROKEN if e.number == failing else self.source)
    assert main(tiny_capture_graph(tmp_path)) == 0
    err = capsys.readouterr().err
    assert err.count("warning: OpenCL device") == 1 and "unknown target CPU 'generic'" in err
    report = json.loads((tmp_path / "r.json").read_text())
    noted = [w for node in report["nodes"] for w in node.get("notes", {}).get("warnings", [])]
    assert any(entries[0].label in w and "unknown target CPU" in w for w in noted)


def test_run_with_no_device_that_builds_exits_2_without_traceback(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(BuildProbe, "source", BROKEN)
    assert main(tiny_capture_graph(tmp_path)) == 2
    err = capsys.readouterr().err
    assert "expected a device that builds OpenCL kernels" in err and "Traceback" not in err
    assert all(e.name in err for e in list_devices(cl)) and "apt-get install pocl-opencl-icd" in err


def test_an_error_that_may_pass_is_not_kept_on_disk(tmp_path, entries):
    class NoKernel(BuildProbe):
        source = "kernel void another_name(global float *x) { }\n"   # builds, but the probe's kernel is missing

    error = NoKernel(cl, tmp_path).verdict(entries[0])
    assert error and "INVALID_KERNEL_NAME" in error
    assert not list(tmp_path.glob("*.json"))                       # the next process probes again
