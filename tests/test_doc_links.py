"""Every link between the docs lands: the file exists and, with ``#anchor``, the heading does
(anchors as GitHub makes them), so a reader who follows one is not left at the top of a page."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
LINK = re.compile(r"\]\(([^)\s]*)\)")
HEADING = re.compile(r"^#{1,6} (.*?)\s*#*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation (but ``-`` and ``_``) dropped,
    spaces → ``-``."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of ``page``'s headings (a repeated one gets ``-1``, ``-2`` … as on GitHub)."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    fenced = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            fenced = not fenced
        m = None if fenced else HEADING.match(line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def broken_links() -> list[str]:
    cache: dict[Path, set[str]] = {}
    bad = []
    for page in PAGES:
        for target in LINK.findall(page.read_text(encoding="utf-8")):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:, rerun+http:
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(ROOT)}: ({target})"
            if not dest.exists():
                bad.append(f"{where}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in cache.setdefault(dest, anchors(dest)):
                bad.append(f"{where}: no heading with that anchor in {dest.relative_to(ROOT)}")
    return bad


def test_every_link_between_the_docs_lands() -> None:
    assert broken_links() == []


def test_the_anchors_are_githubs() -> None:
    assert slug("## 10. Operator authority".lstrip("# ")) == "10-operator-authority"
    assert (
        slug("Message authentication — `telesurg bench auth`, and the latency before/after")
        == "message-authentication--telesurg-bench-auth-and-the-latency-beforeafter"
    )
    assert slug("The pipeline's stages, measured (2026-12-02 14:06–14:49 UTC)") == (
        "the-pipelines-stages-measured-2026-12-02-14061449-utc"
    )
