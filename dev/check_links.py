"""Check every relative link and #anchor in the repository's Markdown files, and every docs page
and section the Python sources name (`docs/fusion.md, "Integrity"`), run by `make lint`.

A link is broken when its file does not exist, or its #anchor names no heading of the target
(anchors as GitHub makes them: lower case, punctuation but '-' and '_' dropped, spaces as '-',
a repeated heading suffixed -1, -2, ...). Links to other sites are not fetched (no network here).
Exit 1 with one line per broken link, 0 when none.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SKIPPED_FOLDERS = {".venv", ".git", "build", "install", "log", "out", "node_modules"}
LINK = re.compile(r"(?<!!)\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^()\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def markdown_files(root: Path) -> list[Path]:
    """Every tracked-looking Markdown file under root, outside venvs and build folders."""
    return sorted(p for p in root.rglob("*.md")
                  if not SKIPPED_FOLDERS.intersection(p.relative_to(root).parts))


def _outside_code(text: str) -> list[str]:
    """The file's lines with fenced code blocks blanked (links there are examples, not links)."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            lines.append("")
            continue
        lines.append("" if fenced else re.sub(r"`[^`]*`", "", line))
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text."""
    text = re.sub(r"`([^`]*)`", r"\1", heading)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor the headings of a Markdown file define."""
    seen: dict[str, int] = {}
    found = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        match = None if fenced else HEADING.match(line)
        if match is None:
            continue
        base = slug(match.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def broken_links(path: Path) -> list[str]:
    """One line per relative link of a Markdown file whose file or anchor does not exist."""
    problems = []
    for number, line in enumerate(_outside_code(path.read_text(encoding="utf-8")), start=1):
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):
                continue  # http:, https:, mailto: - not fetched
            file_part, _, anchor = target.partition("#")
            resolved = (path.parent / file_part).resolve() if file_part else path
            where = f"{path.relative_to(ROOT)}:{number}: {target}"
            if not resolved.exists():
                problems.append(f"{where}: no such file")
            elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
                problems.append(f"{where}: no heading with anchor #{anchor} in {resolved.name}")
    return problems


SOURCE_REFERENCE = re.compile(r"(docs/[a-z0-9_/.-]+?\.md)(?:'s|,)?\s*(?:section\s*)?\"([^\"]+)\"")


def headings(path: Path) -> list[str]:
    """The text of every heading of a Markdown file, lower case."""
    return [match.group(2).lower() for line in path.read_text(encoding="utf-8").splitlines()
            if (match := HEADING.match(line))]


def broken_source_references(path: Path) -> list[str]:
    """One line per docs page a Python file names that does not exist, or a section it quotes
    that begins no heading of that page."""
    problems = []
    text = path.read_text(encoding="utf-8")
    for match in re.finditer(r"docs/[a-z0-9_/.-]+?\.md", text):
        number = text.count("\n", 0, match.start()) + 1
        if _docs_page(match.group(0)) is None:
            problems.append(f"{path.relative_to(ROOT)}:{number}: {match.group(0)}: no such file")
    for match in SOURCE_REFERENCE.finditer(text):
        page = _docs_page(match.group(1))
        number = text.count("\n", 0, match.start()) + 1
        section = match.group(2).lower()
        if page is not None and not any(h.startswith(section) for h in headings(page)):
            problems.append(f"{path.relative_to(ROOT)}:{number}: {match.group(1)}: no section "
                            f"'{match.group(2)}'")
    return problems


def _docs_page(name: str) -> Path | None:
    """A docs page named from the repository (or the shared contracts beside it), if it exists."""
    for base in (ROOT, ROOT.parent / "shared"):
        if (base / name).exists():
            return base / name
    return None


def python_files(root: Path) -> list[Path]:
    """The package's, tests', launch files' and tools' Python sources."""
    return sorted(p for p in root.rglob("*.py")
                  if not SKIPPED_FOLDERS.intersection(p.relative_to(root).parts))


def all_problems(root: Path) -> list[str]:
    """Every broken link of the Markdown files and every broken docs reference of the sources."""
    return ([line for path in markdown_files(root) for line in broken_links(path)]
            + [line for path in python_files(root) for line in broken_source_references(path)])


def main() -> int:
    problems = all_problems(ROOT)
    for line in problems:
        print(line)
    print(f"check_links: {len(problems)} broken link(s) or docs reference(s)", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
