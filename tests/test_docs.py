"""The docs stay true: the stage reference in docs/stages.md is what `btforge stages --markdown` prints, the README
is a short front door that opens with the two CI commands, its links resolve, every picture in the docs has a row
in docs/images/SOURCES.md naming data the project may ship, and no page reads like a development log."""
import re
import sys
from pathlib import Path

from btforge.cli import stage_record, stages_markdown
from btforge.registry import Registry

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
STAGES = ROOT / "docs" / "stages.md"
BEGIN, END = "<!-- stages:begin -->", "<!-- stages:end -->"
README_MAX_LINES = 250


def current_reference() -> str:
    reg = Registry()
    return stages_markdown([stage_record(reg.stages[n]) for n in sorted(reg.stages)])


def test_stage_reference_is_current():
    text = STAGES.read_text()
    section = text[text.index(BEGIN) + len(BEGIN):text.index(END)].strip()
    assert section == current_reference().strip(), "docs/stages.md is stale: run `python tests/test_docs.py`"


def test_readme_opens_with_the_demo_and_test_commands():
    first_block = re.search(r"```bash\n(.*?)```", README.read_text(), re.S).group(1)
    lines = first_block.splitlines()
    assert lines[0].startswith("bash .ci/setup && btforge run graphs/demo.yaml --out out")
    assert lines[1].startswith("bash .ci/setup && python3 -m pytest -q")
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python3 -m pytest" in ci and ".ci/setup" in ci


def test_readme_is_a_front_door_not_a_manual():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): "
                                           "move the detail into a page under docs/ and link it")


def _pages():
    return [README, ROOT / "CONTRIBUTING.md",
            *sorted(p for p in (ROOT / "docs").rglob("*.md") if "incoming" not in p.parts)]


def test_relative_links_and_pictures_resolve():
    broken = []
    for page in _pages():
        if not page.exists():
            continue
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path = target.split("#")[0]
            if not (page.parent / path).exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, "links to missing files:\n" + "\n".join(broken)


# Pictures in the docs show data the project may ship: docs/images/SOURCES.md names each one's data and licence.
SOURCES = ROOT / "docs" / "images" / "SOURCES.md"
PICTURE_FOLDERS = ("docs/images", "docs/wang", "docs/bench")
PICTURE_SUFFIXES = {".png", ".jpg", ".jpeg", ".gif", ".webp", ".svg"}
SHIPPABLE = {"MIT", "procedural, ours", "ours (plot of figures)"}


def _source_rows() -> dict[str, list[str]]:
    """The rows of SOURCES.md's table whose first cell is a backticked file, by that file: [file, data, licence,
    recipe]."""
    rows = {}
    for line in SOURCES.read_text().splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        named = re.fullmatch(r"`([^`]+)`", cells[0]) if line.startswith("|") else None
        if named:
            rows[named.group(1)] = cells
    return rows


def test_every_picture_in_the_docs_names_its_data_and_a_licence_we_may_ship():
    rows = _source_rows()
    pictures = sorted(str(path.relative_to(ROOT)) for folder in PICTURE_FOLDERS for path in (ROOT / folder).rglob("*")
                      if path.suffix.lower() in PICTURE_SUFFIXES)
    unlisted = [p for p in pictures if p not in rows]
    unshippable = [f"{p}: {rows[p][2:3]}" for p in pictures
                   if p in rows and (len(rows[p]) < 4 or rows[p][2] not in SHIPPABLE)]
    gone = [p for p in rows if not (ROOT / p).exists()]
    assert not unlisted, ("pictures without a row in docs/images/SOURCES.md (file, data, licence, how to make it): "
                          + ", ".join(unlisted))
    assert not unshippable, (f"pictures whose data is not ours or MIT (licence cell one of {sorted(SHIPPABLE)}); a "
                             "picture rendered from an unlicensed capture is derived from it:\n" + "\n".join(unshippable))
    assert not gone, "rows of docs/images/SOURCES.md for files that are gone: " + ", ".join(gone)


# Words that date a text: who did what when, instead of what the software does now.
LOG_WORDING = re.compile(
    r"\bthis round\b|\bround \d|\b(second|third|fourth|fifth)[- ]round\b|\bissue's\b|\bthe issue\b|\bissue \d|"
    r"\bengineers?\b|\bsessions?\b|\bmerging\b|\bthe merge\b|\b(is|was|were|be|been) merged\b|\bmerged main\b|"
    r"\bmain (at |before )?`?[0-9a-f]{7}|\bcommit [0-9a-f]{7}", re.I)


def _texts():
    yield from _pages()
    for folder in ("framework", "plugins"):
        for path in sorted((ROOT / folder).rglob("*")):
            if path.suffix in {".py", ".cl", ".js", ".html"} and "__pycache__" not in path.parts:
                yield path


def test_no_development_log_wording_in_docs_help_or_code():
    found = []
    for path in _texts():
        if not path.exists():
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            match = LOG_WORDING.search(line)
            if match:
                found.append(f"{path.relative_to(ROOT)}:{number}: '{match.group(0)}'")
    assert not found, ("development-log wording (say what the software does, not who changed it when; history "
                       "goes in CHANGELOG.md):\n" + "\n".join(found))


if __name__ == "__main__":  # regenerate the reference section
    text = STAGES.read_text()
    head, rest = text.split(BEGIN)
    _, tail = rest.split(END)
    STAGES.write_text(f"{head}{BEGIN}\n{current_reference().strip()}\n{END}{tail}")
    sys.exit(0)
