"""README documents every stage exactly as `btforge stages --markdown` prints it, and opens with the two commands."""
import re
import sys
from pathlib import Path

from btforge.cli import stage_record, stages_markdown
from btforge.registry import Registry

README = Path(__file__).resolve().parents[1] / "README.md"
BEGIN, END = "<!-- stages:begin -->", "<!-- stages:end -->"


def current_reference() -> str:
    reg = Registry()
    return stages_markdown([stage_record(reg.stages[n]) for n in sorted(reg.stages)])


def test_stage_reference_in_readme_is_current():
    text = README.read_text()
    section = text[text.index(BEGIN) + len(BEGIN):text.index(END)].strip()
    assert section == current_reference().strip(), "README's stage reference is stale: run `python tests/test_docs.py`"


def test_readme_opens_with_the_demo_and_test_commands():
    first_block = re.search(r"```bash\n(.*?)```", README.read_text(), re.S).group(1)
    assert "btforge run graphs/demo.yaml" in first_block and "pytest" in first_block
    ci = (README.parent / ".ci" / "run").read_text()
    assert "python3 -m pytest" in ci and ".ci/setup" in ci


if __name__ == "__main__":  # regenerate the reference section
    text = README.read_text()
    head, rest = text.split(BEGIN)
    _, tail = rest.split(END)
    README.write_text(f"{head}{BEGIN}\n{current_reference().strip()}\n{END}{tail}")
    sys.exit(0)
