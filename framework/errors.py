"""One error type for everything a user can get wrong.

A :class:`BtforgeInputError` names the thing at fault (graph node, port, parameter, file, line), says what was
expected and what was found, and hints at the fix.  The CLI prints it as a few plain lines and exits with code 2;
tracebacks are only shown behind ``--debug``.
"""
from __future__ import annotations

import contextlib
import functools
import struct
import warnings
import zipfile
import zlib
from typing import Callable, Iterator, TypeVar


class BtforgeError(Exception):
    """Base of every error btforge raises on purpose."""


class BtforgeInputError(BtforgeError):
    """Bad input: a graph, a parameter, a file or an array that cannot be used as given.

    Parameters
    ----------
    what
        The thing at fault, e.g. ``"node 'fit', port 'stack'"`` or ``"capture/dirs.lp, line 7"``.
    problem
        What is wrong, ideally phrased as ``expected ..., found ...``.
    hint
        How to fix it (optional).
    """

    exit_code = 2

    def __init__(self, what: str, problem: str, hint: str | None = None):
        self.what = what
        self.problem = problem
        self.hint = hint
        super().__init__(self.render())

    def _statement(self) -> str:
        return f"{self.what}: {self.problem}" if self.what else self.problem

    def render(self) -> str:
        """The message, with the hint on its own line (what the CLI prints)."""
        return self._statement() + (f"\n  hint: {self.hint}" if self.hint else "")

    def one_line(self) -> str:
        """The message on one line, the hint in parentheses (for lists of problems)."""
        return self._statement() + (f" ({self.hint})" if self.hint else "")

    def located(self, prefix: str) -> "BtforgeInputError":
        """The same error with ``prefix`` (e.g. the graph node) put in front of what it names."""
        where = f"{prefix}, {self.what}" if self.what else prefix
        return BtforgeInputError(where, self.problem, self.hint)


class BtforgeWarning(UserWarning):
    """A result was produced but the user should know something about it (clamped light, ill-conditioned fit)."""


class DeprecatedNameWarning(BtforgeWarning):
    """A graph or a call used an old name of a stage; it still works, under the new name."""


@contextlib.contextmanager
def collect_warnings() -> Iterator[list[str]]:
    """Collect the text of every :class:`BtforgeWarning` raised in the block (for the run report), and pass
    every warning on afterwards, so the CLI still shows it."""
    texts: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", BtforgeWarning)
        try:
            yield texts
        finally:
            texts.extend(str(w.message) for w in caught if issubclass(w.category, BtforgeWarning))
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


# What a decoder raises on damaged bytes: archive and compression errors, truncation, bad text or numbers (JSON and
# .npy headers raise ValueError), sizes that overflow, lookups of entries the damaged file lacks.
# Pillow also raises SyntaxError for a broken PNG chunk; zipfile raises NotImplementedError for a damaged
# compression method or version, RuntimeError for a damaged encryption flag (JSON: RecursionError, a RuntimeError).
DAMAGED_FILE_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, struct.error, UnicodeError, ValueError,
                       OverflowError, LookupError, OSError, SyntaxError, NotImplementedError, RuntimeError)


@contextlib.contextmanager
def reading_file(path, kind: str, hint: str = "the file is damaged or truncated; write it again") -> Iterator[None]:
    """Turn a decoder's error on a damaged ``path`` into a :class:`BtforgeInputError` naming the file and its
    ``kind`` (e.g. ``"a tile-set archive"``) with what went wrong; input errors raised inside pass unchanged."""
    try:
        yield
    except BtforgeInputError:
        raise
    except FileNotFoundError:
        raise BtforgeInputError(str(path), "file not found", "check the path") from None
    except DAMAGED_FILE_ERRORS as exc:
        detail = str(exc).strip() or "no detail"
        module = type(exc).__module__
        name = type(exc).__name__ if module == "builtins" else f"{module}.{type(exc).__name__}"
        raise BtforgeInputError(str(path), f"cannot be read as {kind} ({name}: {detail[:200]})", hint) from None


Reader = TypeVar("Reader", bound=Callable)


def file_reader(kind: str,
                hint: str = "the file is damaged or truncated; write it again") -> Callable[[Reader], Reader]:
    """Decorate a function whose first argument is a file path with :func:`reading_file`."""
    def decorate(read: Reader) -> Reader:
        @functools.wraps(read)
        def checked(path, *args, **kwargs):
            with reading_file(path, kind, hint):
                return read(path, *args, **kwargs)
        return checked  # type: ignore[return-value]
    return decorate
