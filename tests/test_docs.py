"""The README and docs/: every relative link (and #anchor) resolves; the README stays a short guide whose
test command is the one CI runs."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")  # [text](target) and ![alt](target)


def prose(text: str) -> str:
    """``text`` without its fenced code blocks (a link or heading inside one is not one)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped but hyphens and
    underscores, spaces as hyphens, a repeated one numbered -1, -2, ..."""
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6} +(.+?) *#*$", prose(page.read_text()), flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def test_github_anchors_by_hand(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("# The main job: `jaxusar reproduce`\n## What \"optimal\" means\n## A map's own settings\n"
                    "```\n# not a heading\n```\n## Notes\n## Notes\n")
    assert anchors(page) == {"the-main-job-jaxusar-reproduce", "what-optimal-means", "a-maps-own-settings", "notes",
                             "notes-1"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    links = LINK.findall(prose(page.read_text()))
    assert links, f"{page.relative_to(ROOT)} links nowhere"
    for target in links:
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.relative_to(ROOT)}: {target} -> {dest} does not exist"
        assert ROOT in dest.parents or dest == ROOT, f"{page.relative_to(ROOT)}: {target} leaves the repository"
        if anchor and dest.suffix == ".md":
            assert anchor in anchors(dest), f"{page.relative_to(ROOT)}: no heading #{anchor} in {dest.relative_to(ROOT)}"


def test_the_readme_is_a_short_guide_with_the_test_command_ci_runs():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line.startswith("python3 -m venv")]
    assert len(ci) == 1 and f"\n{ci[0]}\n" in readme, ci
    for page in PAGES[1:]:  # every docs page is linked from the README
        assert f"(docs/{page.name})" in readme, page.name
