"""The docs' link and anchor checker (dev/check_links.py, run by `make lint`): it finds what it
should on small pages, and the repository's own docs pass it."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
_SPEC = importlib.util.spec_from_file_location("check_links", ROOT / "dev" / "check_links.py")
check_links = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(check_links)


def test_anchors_are_made_as_github_makes_them(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# The scan matcher's input (`/scan_match/keyframe_odom`)\n"
                    "## Measured\n## Measured\n```\n# not a heading\n```\n")
    assert check_links.anchors(page) == {
        "the-scan-matchers-input-scan_matchkeyframe_odom", "measured", "measured-1"}


def test_a_missing_file_and_a_missing_anchor_are_reported(tmp_path, monkeypatch):
    monkeypatch.setattr(check_links, "ROOT", tmp_path)
    (tmp_path / "other.md").write_text("## Present\n")
    page = tmp_path / "page.md"
    page.write_text("[a](other.md#present) [b](other.md#absent) [c](gone.md) [d](https://x.org/#y)\n"
                    "```\n[e](in-code.md)\n```\n")
    problems = check_links.broken_links(page)
    assert len(problems) == 2
    assert "other.md#absent: no heading with anchor #absent" in problems[0]
    assert "gone.md: no such file" in problems[1]


def test_a_section_a_source_names_must_exist(tmp_path, monkeypatch):
    monkeypatch.setattr(check_links, "ROOT", tmp_path)
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "fusion.md").write_text("## Integrity\n")
    source = tmp_path / "node.py"
    docs = "docs/"  # split, so that this file itself names no missing page
    source.write_text(f'# {docs}fusion.md, "Integrity"; {docs}fusion.md "Gone"; {docs}none.md\n')
    problems = check_links.broken_source_references(source)
    assert len(problems) == 2
    assert f"{docs}none.md: no such file" in problems[0]
    assert "no section 'Gone'" in problems[1]


def test_the_repository_docs_have_no_broken_link():
    assert check_links.all_problems(ROOT) == []
