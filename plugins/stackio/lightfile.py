"""Light files: the list that says which image of a capture was lit from which direction.

The ``.lp`` layout (relight, RTIBuilder) is a count ``N`` on the first line, then ``N`` rows
``filename x y z`` with ``(x, y, z)`` pointing from the surface toward the light, z up.  A ``.lvp`` file has
rows ``filename lx ly lz vx vy vz``: the light direction, then the direction toward the camera.

Real files are untidy, so the reader accepts decimal commas (``0,5``), file names with spaces (the trailing
numbers are the direction, everything before them is the name), CRLF line ends, UTF-8 or UTF-16 byte-order
marks, trailing whitespace, blank lines, whole-line ``#`` comments (a ``#`` after a row's numbers is not a
comment: names may contain it), Windows paths (``sub\\a.jpg``), and it normalises non-unit vectors.  It does *not* guess when the file disagrees with
itself: a count that does not match the rows, a malformed row or a missing image stops with a
:class:`~btforge.errors.BtforgeInputError` naming the file and line, because pairing a light with the wrong
image silently ruins every fit downstream.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from btforge.atomic import atomic_write_text
from btforge.errors import BtforgeInputError, BtforgeWarning

__all__ = [
    "LightFileEntry",
    "read_light_file",
    "write_light_file",
    "parse_light_list",
    "image_path",
    "HORIZON_TOLERANCE_DEG",
]

#: Directions at most this far below the horizon are treated as calibration noise and clamped to z = 0.
HORIZON_TOLERANCE_DEG = 1.0

# A plain decimal number, with '.' or ',' as the decimal mark.  'nan' and 'inf' are deliberately not numbers
# here: a light direction can never be one, and rejecting them at parse time gives a precise message.
_NUMBER = re.compile(r"^[+-]?(?:\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE][+-]?\d+)?$")


@dataclasses.dataclass(frozen=True)
class LightFileEntry:
    """One row of a light file.

    Attributes
    ----------
    line
        1-based line number of the row in the file (for error messages).
    filename
        The image name exactly as written (it may contain spaces), relative to the light file's folder.
    light
        Unit direction toward the light, ``z >= 0``.
    view
        Unit direction toward the camera for ``.lvp`` files, else ``None``.
    """

    line: int
    filename: str
    light: tuple[float, float, float]
    view: tuple[float, float, float] | None = None


def image_path(light_file: str | os.PathLike, filename: str) -> Path:
    """Where the image ``filename`` listed in ``light_file`` lives: names are relative to the file's folder
    (or to the capture folder itself, for a BTF folder)."""
    source = Path(light_file)
    folder = source if source.is_dir() else source.parent
    if "\\" in filename and os.sep == "/" and not (folder / filename).exists():
        # Written on Windows: 'sub\a.jpg' means the folder 'sub' (a POSIX name may contain a backslash, so
        # that reading is tried only when the literal one does not exist).
        filename = filename.replace("\\", "/")
    return folder / filename


# Bonn UBO-style BTF image names carry the angles in degrees: tl<theta light>_pl<phi light>_tv<theta view>_pv<phi view>
_UBO_NAME = re.compile(r"tl(?P<tl>[+-]?\d+(?:\.\d+)?)_pl(?P<pl>[+-]?\d+(?:\.\d+)?)_"
                       r"tv(?P<tv>[+-]?\d+(?:\.\d+)?)_pv(?P<pv>[+-]?\d+(?:\.\d+)?)", re.IGNORECASE)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")


def _from_angles(theta_deg: float, phi_deg: float) -> tuple[float, float, float]:
    theta, phi = math.radians(theta_deg), math.radians(phi_deg)
    return (math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta))


def read_btf_folder(folder: str | os.PathLike) -> list[LightFileEntry]:
    """The images of a Bonn UBO-style BTF folder, whose names carry the light and view angles.

    Names look like ``tl15_pl0_tv30_pv120.png`` (theta from the zenith and phi in degrees, for light and view;
    any prefix or suffix around that pattern is allowed).  Entries are ordered by view, then light, so every view
    lists its lights in the same order; ``line`` is the position in that order.
    """
    folder = Path(folder)
    return btf_entries([path.name for path in sorted(folder.iterdir())], str(folder))


def btf_entries(names: Iterable[str], where: str) -> list[LightFileEntry]:
    """Entries for the image ``names`` (of a folder, or of a UBO2003 zip archive, paths inside it allowed)
    whose names carry the angles; other names are ignored.  Ordered by view, then light."""
    found = []
    for name in names:
        stem, suffix = os.path.splitext(name)
        if suffix.lower() not in IMAGE_SUFFIXES:
            continue
        match = _UBO_NAME.search(os.path.basename(stem))
        if match is None:
            continue
        angles = {k: float(v) for k, v in match.groupdict().items()}
        what = f"{where}/{name}"
        light = _checked_direction(_from_angles(angles["tl"], angles["pl"]), what, "light")
        view = _checked_direction(_from_angles(angles["tv"], angles["pv"]), what, "view")
        found.append(((angles["tv"], angles["pv"], angles["tl"], angles["pl"]), name, light, view))
    if not found:
        raise BtforgeInputError(where, "expected images named like tl15_pl0_tv30_pv120.png (a UBO-style BTF "
                                "folder or zip), found none", "give a .lp/.lvp light file, or a folder or zip of such images")
    found.sort(key=lambda item: item[0])
    return [LightFileEntry(i, name, light, view) for i, (_, name, light, view) in enumerate(found, 1)]


def is_dfmf_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a Bonn ``.btf`` file (by its suffix; the signature is checked on reading).  It lives
    here, not beside its reader (``ubo2014``), so that telling a light file apart does not import that reader."""
    return Path(path).suffix.lower() == ".btf" and Path(path).is_file()


def is_btf_zip(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a zip archive (the Bonn UBO2003 download layout) rather than a light file."""
    return Path(path).suffix.lower() == ".zip"


def read_capture_index(path: str | os.PathLike, *, require_images: bool = True) -> list[LightFileEntry]:
    """The entries of a capture: a ``.lp``/``.lvp`` light file, or a UBO-style BTF folder or zip archive."""
    if Path(path).is_dir():
        return read_btf_folder(path)
    if is_btf_zip(path):
        import zipfile
        try:
            with zipfile.ZipFile(path) as archive:
                names = [info.filename for info in archive.infolist() if not info.is_dir()]
        except (OSError, zipfile.BadZipFile) as exc:
            raise BtforgeInputError(str(path), f"cannot read the zip archive ({exc})",
                                    "the download may be incomplete; fetch it again") from None
        return btf_entries(names, str(path))
    return read_light_file(path, require_images=require_images)


# ----------------------------------------------------------------------------------------------- checks


def _is_number(token: str) -> bool:
    return bool(_NUMBER.match(token))


def _to_float(token: str) -> float:
    return float(token.replace(",", "."))


def _checked_direction(vector: Sequence[float], what: str, role: str) -> tuple[float, float, float]:
    """Normalise ``vector`` and enforce the upper hemisphere.

    Parameters
    ----------
    vector
        Three finite numbers.
    what
        Where the vector came from, e.g. ``"capture/dirs.lp, line 7"``; used in errors and warnings.
    role
        ``"light"`` or ``"view"``, for the messages.

    Returns
    -------
    tuple of float
        The unit vector, with a slightly negative z clamped to 0.
    """
    x, y, z = (float(v) for v in vector)
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise BtforgeInputError(what, f"expected a finite {role} direction, found ({x}, {y}, {z})",
                                "replace the NaN/Inf value with the measured direction")
    norm = math.sqrt(x * x + y * y + z * z)
    if norm < 1e-9:
        raise BtforgeInputError(what, f"expected a non-zero {role} direction, found ({x:g}, {y:g}, {z:g})",
                                "a direction needs a length; re-run the light calibration for this image")
    x, y, z = x / norm, y / norm, z / norm
    if z < 0.0:
        degrees_below = math.degrees(math.asin(min(1.0, -z)))
        if degrees_below > HORIZON_TOLERANCE_DEG:
            raise BtforgeInputError(
                what,
                f"expected a {role} direction above the horizon (z >= 0), found z = {z:.4f} "
                f"({degrees_below:.1f} degrees below)",
                f"directions point from the surface toward the {'camera' if role == 'view' else 'light'} with z up; "
                "check the sign convention "
                "of the tool that wrote this file, or drop the image")
        warnings.warn(
            f"{what}: {role} direction is {degrees_below:.2f} degrees below the horizon; clamped to z = 0",
            BtforgeWarning, stacklevel=3)
        horizontal = math.hypot(x, y)
        x, y, z = x / horizontal, y / horizontal, 0.0
    return (x, y, z)


# ----------------------------------------------------------------------------------------------- reading


def _decode(raw: bytes) -> str:
    # Light files come from Windows tools as often as not: accept a BOM (UTF-8, or UTF-16 as Notepad's "Unicode"
    # writes), fall back to Latin-1 for names written in a legacy code page rather than refusing the whole file
    # over one accented file name.
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        try:
            return raw.decode("utf-16")
        except UnicodeDecodeError:
            pass
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _parse_row(line: str, n_numbers: int, what: str, kind: str) -> tuple[str, list[float]]:
    """Split a row into the file name (as written, inner spaces kept) and its ``n_numbers`` trailing numbers."""
    spans = [(m.start(), m.group()) for m in re.finditer(r"\S+", line)]
    tokens = [t for _, t in spans]
    shape = f"a file name and {n_numbers} numbers"
    hint = (f"each row of a {kind} file is 'filename " + " ".join(["x y z", "vx vy vz"][: n_numbers // 3]) + "'")
    if n_numbers == 3:
        hint += "; a file that also lists view directions (6 numbers) must be named .lvp"
    if len(tokens) < n_numbers + 1:
        raise BtforgeInputError(what, f"expected {shape}, found {len(tokens)} field{'s' * (len(tokens) != 1)}",
                                hint)
    trailing = 0
    for token in reversed(tokens):
        if not _is_number(token):
            break
        trailing += 1
    if trailing > n_numbers:
        if trailing == len(tokens) == n_numbers + 1:
            # A bare numeric file name ("0017 0.1 0.2 0.97"): unusual, but not ambiguous.
            trailing = n_numbers
        else:
            raise BtforgeInputError(what, f"expected {n_numbers} numbers after the file name, found {trailing}",
                                    hint)
    if trailing < n_numbers:
        culprit = tokens[-trailing - 1]
        numbers_before = len(tokens) - trailing - 2 >= 0 and _is_number(tokens[-trailing - 2])
        looks_like_file = bool(re.search(r"\.[A-Za-z][A-Za-z0-9]{1,4}$", culprit))
        if looks_like_file and not numbers_before:
            raise BtforgeInputError(what, f"expected {n_numbers} numbers after the file name, found {trailing}",
                                    hint)
        raise BtforgeInputError(what, f"expected a number, found {culprit!r}",
                                "use plain decimal numbers such as 0.25 (a decimal comma, 0,25, is also accepted)")
    name_end = spans[-n_numbers][0]
    name = line[: name_end].strip()
    return name, [_to_float(t) for t in tokens[-n_numbers:]]


def read_light_file(path: str | os.PathLike, *, require_images: bool = True) -> list[LightFileEntry]:
    """Read a ``.lp`` (or ``.lvp``) light file.

    Parameters
    ----------
    path
        The light file.  Rows of a ``.lvp`` file carry 6 numbers (light, then view direction), any other
        extension 3.
    require_images
        Check that every listed image exists (relative to the light file's folder).

    Returns
    -------
    list of LightFileEntry
        One entry per row, in file order, with unit directions.

    Raises
    ------
    BtforgeInputError
        For an unreadable file, a count that disagrees with the rows, a malformed row, a zero or clearly
        downward direction, or a missing image; ``what`` is ``"<path>, line <n>"``.

    Warns
    -----
    BtforgeWarning
        For a direction at most one degree below the horizon, which is clamped to z = 0.
    """
    path_text = str(path)
    path = Path(path)
    kind = ".lvp" if path.suffix.lower() == ".lvp" else ".lp"
    count, count_line, entries, problems = _read_rows(path_text, _decode(_read_bytes(path, path_text)), kind)
    count_problem = _count_problem(path_text, count, count_line, entries)
    if count_problem is not None:
        problems.insert(0, count_problem)
    bad_rows = {p.what for p in problems}
    entries = [e for e in entries if f"{path_text}, line {e.line}" not in bad_rows]
    if require_images:
        problems += _missing_images(path, path_text, entries)
    if len(problems) == 1:
        raise problems[0]
    if problems:  # every bad row, the count and missing images: reported together
        raise BtforgeInputError(path_text, f"{len(problems)} problems:\n  - " + "\n  - ".join(
            p.one_line() for p in problems))
    return entries


def _read_bytes(path: Path, path_text: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise BtforgeInputError(path_text, "light file not found", "check the path (it is relative to the "
                                "current directory unless absolute)") from None
    except OSError as exc:
        raise BtforgeInputError(path_text, f"cannot read the light file: {exc.strerror or exc}") from None


def _read_rows(path_text: str, text: str, kind: str) -> tuple[int, int, list[LightFileEntry], list[BtforgeInputError]]:
    """The count (and its line), one entry per row (a placeholder for a bad row, so the count still compares)
    and the problems of the bad rows.  Blank and ``#`` lines are skipped; a ``.lvp`` row adds a view direction."""
    is_lvp = kind == ".lvp"
    count: int | None = None
    count_line = 0
    entries: list[LightFileEntry] = []
    problems: list[BtforgeInputError] = []
    for number, row in enumerate(text.splitlines(), start=1):
        row = row.strip()
        if not row or row.startswith("#"):
            continue
        what = f"{path_text}, line {number}"
        if count is None:
            if not re.fullmatch(r"\d+", row):
                raise BtforgeInputError(what, f"expected the number of images, found {row[:60]!r}",
                                        f"the first line of a {kind} file is the image count, e.g. '72'")
            count, count_line = int(row), number
            continue
        try:
            name, numbers = _parse_row(row, 6 if is_lvp else 3, what, kind)
            light = _checked_direction(numbers[:3], what, "light")
            view = _checked_direction(numbers[3:], what, "view") if is_lvp else None
        except BtforgeInputError as exc:
            problems.append(exc)
            entries.append(LightFileEntry(number, "", (0.0, 0.0, 1.0), None))
            continue
        entries.append(LightFileEntry(number, name, light, view))
    if count is None:
        raise BtforgeInputError(path_text, "expected the number of images on the first line, found an empty file",
                                f"a {kind} file is a count, then one row per image")
    return count, count_line, entries, problems


def _count_problem(path_text: str, count: int, count_line: int,
                   entries: list[LightFileEntry]) -> BtforgeInputError | None:
    """What is wrong with the count on the first line, given the rows that follow (None: nothing)."""
    count_what = f"{path_text}, line {count_line}"
    if count == 0:
        return BtforgeInputError(count_what, "expected at least one image, found a count of 0")
    if count == len(entries):
        return None
    problem = f"the count says {count} images, but {len(entries)} rows follow"
    if count < len(entries):
        problem += f" (the first extra row is line {entries[count].line})"
    return BtforgeInputError(count_what, problem, "fix the count or the rows; btforge never guesses which light "
                             "belongs to which image")


def _missing_images(path: Path, path_text: str, entries: Iterable[LightFileEntry]) -> list[BtforgeInputError]:
    """One error per listed image that does not exist, each naming its line (with a did-you-mean)."""
    folder = path.parent
    listing: list[str] | None = None
    missing = []
    for entry in entries:
        if image_path(path, entry.filename).is_file():
            continue
        if listing is None:
            try:
                listing = sorted(os.listdir(folder or "."))
            except OSError:
                listing = []
        hint = "image names are relative to the light file's folder"
        base_name = re.split(r"[\\/]", entry.filename)[-1]  # a path written on another machine: C:\\cap\\a.jpg
        same_but_case = [f for f in listing if f.lower() in (entry.filename.lower(), base_name.lower())]
        close = same_but_case or difflib.get_close_matches(base_name, listing, n=1)
        if close:
            hint = f"did you mean {close[0]!r}? " + hint
        missing.append(BtforgeInputError(f"{path_text}, line {entry.line}", f"expected the image {entry.filename!r} "
                                         f"in {str(folder) or '.'}, found no such file", hint))
    return missing


def parse_light_list(value: Any, *, name: str = "lights", role: str = "light") -> np.ndarray:
    """Light directions given inline (a YAML list of ``[x, y, z]``) as an ``(N, 3)`` float32 array of unit vectors.

    The same rules as for a light file apply: non-unit vectors are normalised, a direction within one degree
    below the horizon is clamped (with a :class:`~btforge.errors.BtforgeWarning`), zero and clearly downward
    vectors are errors.

    Parameters
    ----------
    value
        A sequence of 3-number sequences (or an ``(N, 3)`` array).
    name
        What the list is called in messages, e.g. ``"node 'render', parameter 'lights'"``.
    """
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise BtforgeInputError(name, f"expected a list of [x, y, z] directions, found {type(value).__name__}",
                                "write e.g. [[0, 0, 1], [0.5, 0, 0.87]]")
    if len(value) == 0:
        raise BtforgeInputError(name, "expected at least one direction, found an empty list")
    rows = []
    for index, item in enumerate(value):
        what = f"{name}, entry {index}"
        if isinstance(item, (str, bytes)) or not isinstance(item, Sequence) or len(item) != 3:
            found = f"{len(item)} values" if isinstance(item, Sequence) and not isinstance(item, str) else repr(item)
            raise BtforgeInputError(what, f"expected [x, y, z], found {found}")
        for component in item:
            # bool is an int subclass; 'true' in YAML is a typo, not the number 1.
            if isinstance(component, bool) or not isinstance(component, (int, float, np.integer, np.floating)):
                raise BtforgeInputError(what, f"expected a number, found {component!r}")
        rows.append(_checked_direction(item, what, role))
    return np.asarray(rows, dtype=np.float32)


# ----------------------------------------------------------------------------------------------- writing


def _format_number(value: float) -> str:
    # 9 significant digits round-trip float32 exactly; '+ 0.0' turns -0 into 0 so files stay tidy.
    return f"{float(value) + 0.0:.9g}"


def write_light_file(path: str | os.PathLike, filenames: Sequence[str], lights: Any, views: Any = None) -> None:
    """Write a light file atomically: ``.lp`` rows, or ``.lvp`` rows (light then view) when ``views`` is given.

    Parameters
    ----------
    path
        Destination; must end in ``.lvp`` exactly when ``views`` is given, so the reader expects the right
        number of columns.
    filenames
        Image names relative to the light file's folder, one per row.
    lights
        ``(N, 3)`` directions toward the light (normalised on writing).
    views
        Optional ``(N, 3)`` directions toward the camera.
    """
    path_text = str(path)
    is_lvp = Path(path).suffix.lower() == ".lvp"
    if (views is not None) != is_lvp:
        raise BtforgeInputError(path_text,
                                "expected a .lvp name when view directions are given and a .lp name otherwise, "
                                f"found {Path(path).suffix or 'no extension'} with views={'given' if views is not None else 'None'}",
                                "readers decide between 3 and 6 numbers per row from the extension")
    names = [os.fspath(f) for f in filenames]
    light_rows = parse_light_list(np.asarray(lights, dtype=np.float64), name=f"{path_text}, lights")
    if len(names) != len(light_rows):
        raise BtforgeInputError(path_text, f"expected one light per file name, found {len(names)} names and "
                                f"{len(light_rows)} lights")
    view_rows = None
    if views is not None:
        view_rows = np.asarray(views, dtype=np.float64)
        if view_rows.shape != (len(names), 3):
            raise BtforgeInputError(path_text, f"expected views of shape ({len(names)}, 3), found {view_rows.shape}")
        view_rows = np.asarray([_checked_direction(v, f"{path_text}, view {i}", "view")
                                for i, v in enumerate(view_rows)])
    for index, name in enumerate(names):
        # Anything the reader would read back differently is refused rather than written.
        if (not name or name != name.strip() or any(c in name for c in "\r\n\t\v\f")
                or name.startswith("#")):
            raise BtforgeInputError(f"{path_text}, file name {index}",
                                    f"expected a name without leading/trailing whitespace, tabs, line breaks or a "
                                    f"leading '#', found {name!r}", "rename the image")

    lines = [str(len(names))]
    kind = "light-and-view" if is_lvp else "light"
    for index, name in enumerate(names):
        numbers = list(light_rows[index]) + (list(view_rows[index]) if view_rows is not None else [])
        line = name + " " + " ".join(_format_number(v) for v in numbers)
        try:
            read_back = _parse_row(line, len(numbers), f"{path_text}, file name {index}", kind)[0]
        except BtforgeInputError:
            read_back = None
        if read_back != name:  # e.g. a name ending in a number ('take 2') would lose it to the directions
            raise BtforgeInputError(f"{path_text}, file name {index}",
                                    f"expected a name the reader splits off its numbers unchanged, found {name!r}",
                                    "rename the image so its name does not end in a number (e.g. 'take 2.png')")
        lines.append(line)
    atomic_write_text(path, "\n".join(lines) + "\n")
