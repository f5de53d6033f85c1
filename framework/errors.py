"""One error type for everything a user can get wrong.

A :class:`BtforgeInputError` names the thing at fault (graph node, port, parameter, file, line), says what was
expected and what was found, and hints at the fix.  The CLI prints it as a few plain lines and exits with code 2;
tracebacks are only shown behind ``--debug``.
"""
from __future__ import annotations

import contextlib
import warnings
from typing import Iterator


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
