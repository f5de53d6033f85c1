"""Mutation fuzzing of btforge's file readers: mutations, the cases, and worker processes that run them.

A case copies a set of valid files btforge wrote itself into a fresh folder, damages one of them, and runs a reader
the way a user would (``btforge info FILE``, a one-node graph under ``btforge run``, or a stage's reader function).
It passes when it ends in a clean read or a clean refusal: exit code 0 or 2 with no traceback and no "internal
error".  Cases run in worker processes (``python fuzzing.py worker``), one case at a time each, so a crash in native
code (a segmentation fault) or a hang is recorded as that case's failure, and the worker is replaced.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import queue
import random
import re
import select
import shutil
import subprocess
import sys
import threading
import zipfile
from pathlib import Path

# ----------------------------------------------------------------------------------------------- mutations

TEXT_SUFFIXES = (".lp", ".lvp", ".json", ".yaml", ".obj", ".rti", ".ply")
HOSTILE_NUMBERS = ("1e308", "-1e308", "nan", "NaN", "inf", "-inf", "-1", "0", "99999999999", "-2147483649",
                   "4294967296", "1e-320", "0x10", "3.5", "", "-0")
NUMBER = re.compile(rb"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _bit_flips(data: bytearray, rng: random.Random) -> None:
    for _ in range(rng.randint(1, 8)):
        i = rng.randrange(len(data))
        data[i] ^= 1 << rng.randrange(8)


def _byte_changes(data: bytearray, rng: random.Random) -> None:
    for _ in range(rng.randint(1, 6)):
        data[rng.randrange(len(data))] = rng.choice((0, 0xFF, 0x7F, 0x80, rng.randrange(256)))


def _truncate(data: bytearray, rng: random.Random) -> None:
    del data[rng.randrange(len(data)):]


def _insert(data: bytearray, rng: random.Random) -> None:
    at = rng.randrange(len(data) + 1)
    data[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))


def _duplicate_chunk(data: bytearray, rng: random.Random) -> None:
    start = rng.randrange(len(data))
    chunk = data[start:start + rng.randint(1, 512)]
    at = rng.randrange(len(data) + 1)
    data[at:at] = chunk


def _delete_chunk(data: bytearray, rng: random.Random) -> None:
    start = rng.randrange(len(data))
    del data[start:start + rng.randint(1, 256)]


def _hostile_number(data: bytearray, rng: random.Random) -> None:
    """One number written as text (a header count, a coordinate, a JSON field) replaced by a hostile one."""
    head = bytes(data[:65536])  # headers live at the start; the body of a binary file is no text
    numbers = list(NUMBER.finditer(head))
    if not numbers:
        _byte_changes(data, rng)
        return
    match = rng.choice(numbers)
    data[match.start():match.end()] = rng.choice(HOSTILE_NUMBERS).encode()


BYTE_MUTATIONS = (_bit_flips, _byte_changes, _truncate, _insert, _duplicate_chunk, _delete_chunk)


def mutate_bytes(data: bytes, rng: random.Random, text: bool) -> tuple[bytes, str]:
    """``data`` damaged by one mutation (hostile numbers more often for text formats), and its name."""
    mutations = BYTE_MUTATIONS + ((_hostile_number,) * 4 if text else (_hostile_number,))
    mutation = rng.choice(mutations)
    out = bytearray(data or b"\0")
    mutation(out, rng)
    return bytes(out), mutation.__name__.strip("_")


def mutate_zip_member(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A well-formed ZIP (checksums right) with one member damaged: past the archive layer into the decoder."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        members = [(info, archive.read(info)) for info in archive.infolist()]
    pick = rng.randrange(len(members))
    name = members[pick][0].filename
    damaged, how = mutate_bytes(members[pick][1], rng, text=name.endswith((".json", ".npy")))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        for k, (info, content) in enumerate(members):
            archive.writestr(info, damaged if k == pick else content)
    return out.getvalue(), f"{how} in member {name}"


def mutate(data: bytes, suffix: str, rng: random.Random) -> tuple[bytes, str]:
    if data[:2] == b"PK" and rng.random() < 0.5:
        with contextlib.suppress(zipfile.BadZipFile):
            return mutate_zip_member(data, rng)
    return mutate_bytes(data, rng, text=suffix in TEXT_SUFFIXES)


# ----------------------------------------------------------------------------------------------- cases


@dataclasses.dataclass(frozen=True)
class Reader:
    """One way btforge reads a kind of file: the files a case may damage and how the reader is run.

    ``argv`` is a ``btforge`` command line (``{dir}`` = the case's folder), or ``call`` a ``module:function`` that
    is given the entry file's path (a stage's reader, for files no one-node graph can read alone).
    """

    name: str
    members: tuple[str, ...]           # files (relative to the seed folder) a case may damage
    argv: tuple[str, ...] = ()
    call: str = ""
    entry: str = ""


@dataclasses.dataclass(frozen=True)
class Case:
    reader: str
    member: str
    seed: int


@dataclasses.dataclass
class Outcome:
    case: Case
    verdict: str                       # "read", "refused", or a failure: "crash", "hang", "traceback", ...
    detail: str = ""
    mutation: str = ""

    @property
    def clean(self) -> bool:
        return self.verdict in ("read", "refused")


def make_cases(readers: list[Reader], per_reader: int, seed: int) -> list[Case]:
    rng = random.Random(seed)
    return [Case(r.name, rng.choice(r.members), rng.randrange(2 ** 31)) for r in readers for _ in range(per_reader)]


# ----------------------------------------------------------------------------------------------- worker side


def _run_cli(argv: list[str]) -> tuple[int, str]:
    from btforge.cli import main
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


def _run_call(target: str, path: str) -> tuple[int, str]:
    """A reader function as a stage calls it: its input error is the refusal the CLI would print (exit code 2)."""
    import importlib

    from btforge.errors import BtforgeInputError
    module, _, function = target.partition(":")
    try:
        importlib.import_module(module).__dict__[function](path)
    except BtforgeInputError as exc:
        return 2, f"error: {exc.render()}"
    return 0, ""


def crash(path: str) -> None:
    """A reader that dies as native code does on a bad file (for the harness's own test)."""
    import signal
    os.kill(os.getpid(), signal.SIGSEGV)


def verdict_of(code: int, err: str) -> tuple[str, str]:
    if "Traceback" in err:
        return "traceback", err[-400:]
    if "internal error" in err:
        return "internal error", err.strip()[-400:]
    if code == 0:
        return "read", ""
    refusal = [line for line in err.splitlines() if line.startswith("error: ") or " ... error: " in line]
    if code == 2 and refusal:
        return "refused", refusal[0][:300]
    return f"exit code {code}", err.strip()[-400:]


def run_case(reader: Reader, case: Case, seed_dir: Path, scratch: Path, mutate_member: bool = True) -> dict:
    """Copy the seed files, damage ``case.member``, run the reader; the outcome as a JSON-able dict."""
    folder = scratch / f"case{case.seed}"
    shutil.copytree(seed_dir, folder, symlinks=True)
    try:
        how = "none"
        if mutate_member:
            target = folder / case.member
            damaged, how = mutate(target.read_bytes(), target.suffix.lower(), random.Random(case.seed))
            target.write_bytes(damaged)
        try:
            if reader.call:
                code, err = _run_call(reader.call, str(folder / reader.entry))
            else:
                code, err = _run_cli([a.replace("{dir}", str(folder)) for a in reader.argv])
        except BaseException as exc:  # escaped the CLI's own handling: a failure, whatever it is
            code, err = 1, f"Traceback: {type(exc).__name__}: {exc}"
        verdict, detail = verdict_of(code, err)
        return {"verdict": verdict, "detail": detail, "mutation": how}
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def worker_main() -> None:
    """Read ``{"reader": {...}, "case": {...}, "seed_dir", "scratch"}`` lines; answer one JSON line per case."""
    import warnings
    warnings.simplefilter("ignore")
    # answers go out on a private copy of stdout: native code printing to fd 1 cannot garble them
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
    for line in sys.stdin:
        job = json.loads(line)
        reader = Reader(**{k: tuple(v) if isinstance(v, list) else v for k, v in job["reader"].items()})
        result = run_case(reader, Case(**job["case"]), Path(job["seed_dir"]), Path(job["scratch"]))
        answers.write(json.dumps(result) + "\n")
        answers.flush()


# ----------------------------------------------------------------------------------------------- parent side


class Worker:
    """One worker process; replaced after a crash or a hang."""

    def __init__(self, env: dict[str, str]):
        self.env = env
        self.process = None
        self.start()

    def start(self) -> None:
        self.process = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "worker"],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                        env=self.env, text=True, bufsize=1)

    def stop(self) -> None:
        if self.process and self.process.poll() is None:
            self.process.kill()
        if self.process:
            self.process.wait()

    def run(self, job: dict, timeout: float) -> dict:
        try:
            self.process.stdin.write(json.dumps(job) + "\n")
            self.process.stdin.flush()
        except BrokenPipeError:
            pass
        ready, _, _ = select.select([self.process.stdout], [], [], timeout)
        line = self.process.stdout.readline() if ready else ""
        if line:
            return json.loads(line)
        if not ready:
            self.stop()
            self.start()
            return {"verdict": "hang", "detail": f"no answer within {timeout:.0f} s"}
        code = self.process.wait()
        self.start()
        return {"verdict": "crash", "detail": f"worker died with exit code {code}"}


def run_cases(readers: list[Reader], cases: list[Case], seed_dir: Path, scratch: Path, *, workers: int = 2,
              timeout: float = 60.0, env: dict[str, str] | None = None) -> list[Outcome]:
    """Run ``cases`` on ``workers`` worker processes; one :class:`Outcome` per case, in order."""
    by_name = {r.name: r for r in readers}
    todo: queue.Queue = queue.Queue()
    for index, case in enumerate(cases):
        todo.put((index, case))
    outcomes: list[Outcome | None] = [None] * len(cases)

    def serve(worker: Worker) -> None:
        try:
            while True:
                try:
                    index, case = todo.get_nowait()
                except queue.Empty:
                    return
                job = {"reader": dataclasses.asdict(by_name[case.reader]), "case": dataclasses.asdict(case),
                       "seed_dir": str(seed_dir), "scratch": str(scratch)}
                got = worker.run(job, timeout)
                if "mutation" not in got:  # the worker died: replay the (deterministic) mutation to name it
                    data = (seed_dir / case.member).read_bytes()
                    got["mutation"] = mutate(data, Path(case.member).suffix.lower(), random.Random(case.seed))[1]
                outcomes[index] = Outcome(case, got["verdict"], got.get("detail", ""), got.get("mutation", ""))
        finally:
            worker.stop()

    pool = [Worker(env or dict(os.environ)) for _ in range(max(1, workers))]
    threads = [threading.Thread(target=serve, args=(w,)) for w in pool]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return [o for o in outcomes if o is not None]


def summary(outcomes: list[Outcome]) -> dict[str, dict[str, int]]:
    """Per reader: how many cases were read, refused, and failed."""
    table: dict[str, dict[str, int]] = {}
    for o in outcomes:
        row = table.setdefault(o.case.reader, {"cases": 0, "read": 0, "refused": 0, "failed": 0})
        row["cases"] += 1
        row[o.verdict if o.clean else "failed"] += 1
    return table


if __name__ == "__main__" and sys.argv[1:] == ["worker"]:
    worker_main()
