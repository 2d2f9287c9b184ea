"""docs/messages.md is what `telesurg docs messages` generates from the message classes."""

from __future__ import annotations

from pathlib import Path

import pytest
from telesurg.services.docs import DEFAULT_OUT, HEADER_FIELDS, TEMPLATE, main, message_page, type_text
from telesurg.shared.messages import MESSAGE_TYPES, SCHEMA_VERSION


def test_committed_messages_md_is_the_generated_page() -> None:
    assert DEFAULT_OUT.read_text(encoding="utf-8") == message_page(), (
        "docs/messages.md drifted from the message classes: run `telesurg docs messages`"
    )


def test_check_mode_tells_a_stale_page(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "messages.md"
    assert main(["messages", "--out", str(out), "--check"]) == 1
    assert main(["messages", "--out", str(out)]) == 0
    assert main(["messages", "--out", str(out), "--check"]) == 0
    out.write_text(out.read_text().replace("| `follow` |", "| `folow` |", 1))
    assert main(["messages", "--out", str(out), "--check"]) == 1
    assert "out of date" in capsys.readouterr().err


def test_every_message_field_and_the_version_are_on_the_page() -> None:
    page = message_page()
    assert f"the integer `{SCHEMA_VERSION}`" in page and "must be `1`" not in page
    for s in HEADER_FIELDS:
        assert f"| `{s.wire}` | `{s.name}` |" in page
    for tag, cls in MESSAGE_TYPES.items():
        assert f"### `{tag}` — `{cls.__name__}`" in page
        for s in cls.FIELDS:
            unit = s.unit or "—"
            assert f"| `{s.wire}` | `{s.name}` | {type_text(s)} | {unit} |" in page, (tag, s.name)


def test_an_example_that_no_longer_decodes_fails_the_generation() -> None:
    text = TEMPLATE.read_text(encoding="utf-8").replace('"valid_for_ms": 250.0', '"valid_for_ms": 0.0')
    with pytest.raises(ValueError, match="valid_for_ms"):
        message_page(text)


def test_a_message_without_a_section_gets_one_and_an_unknown_placeholder_is_an_error() -> None:
    text = TEMPLATE.read_text(encoding="utf-8").replace("<!-- generated: message heartbeat -->", "")
    assert "### `heartbeat` — `Heartbeat`" in message_page(text)
    with pytest.raises(ValueError, match="placeholder"):
        message_page(text + "\n<!-- generated: message nope -->\n")


def test_a_key_without_a_row_in_the_keys_table_fails_the_generation() -> None:
    text = TEMPLATE.read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith("| `console/<m>/clutch` |"))
    with pytest.raises(ValueError, match="console/<m>/clutch"):
        message_page(text.replace(row + "\n", ""))


# --------------------------------------------------------------------------- performance.md


def test_committed_performance_md_is_the_generated_page() -> None:
    from telesurg.services.docs.performance import DEFAULT_OUT as PERF_OUT
    from telesurg.services.docs.performance import performance_page

    assert PERF_OUT.read_text(encoding="utf-8") == performance_page(), (
        "docs/performance.md drifted from the result files: run `telesurg docs performance`"
    )


def test_every_performance_row_names_a_command_the_cli_takes() -> None:
    """Each row's command parses (as the docs' command lines do) and writes the file the row reads."""
    from telesurg.services.cli import COMMANDS
    from telesurg.services.docs.performance import RESULTS
    from test_docs_commands import parse_only

    for r in RESULTS:
        words = r.command.split()
        if words[0] != "telesurg":  # a test that writes the file: TELESURG_PERF_DIR=DIR pytest …
            assert words[0] == f"TELESURG_PERF_DIR={Path(r.data).parent}", r.command
            continue
        assert r.data in words, f"{r.command}: does not write {r.data}"
        module = COMMANDS[words[1]][0]
        problem = parse_only(module, tuple(words[2:]))
        assert problem is None, f"{r.command}: {problem}"


def test_a_missing_result_file_fails_the_generation(tmp_path: Path) -> None:
    from telesurg.services.docs import performance

    gone = performance.Result("x", "docs/data/perf/no-such.json", "telesurg bench sim --json x", lambda d: "")
    with pytest.raises(ValueError, match=r"no-such\.json"):
        performance._row(gone)
    assert main(["performance", "--out", str(tmp_path / "p.md")]) == 0
    assert main(["performance", "--out", str(tmp_path / "p.md"), "--check"]) == 0


# --------------------------------------------------------------------------- data and images

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
ASSET_DIRS = ("docs/data", "docs/img")


def _referenced() -> dict[str, str]:
    """Every docs/data or docs/img path a page names (links, images, commands), by the page."""
    import re

    out: dict[str, str] = {}
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for hit in re.finditer(
            r"(?<![\w/.-])((?:\.\./)*(?:docs/)?(?:data|img)/[\w./-]+?)(?=[)\s`\"'\],;|]|$)", text
        ):
            name = hit.group(1)
            path = (ROOT / name if name.startswith("docs/") else page.parent / name).resolve()
            out[path.relative_to(ROOT).as_posix().rstrip("/")] = page.relative_to(ROOT).as_posix()
    return out


def test_every_data_file_and_image_is_used_by_a_page() -> None:
    refs = _referenced()
    unused = [
        f.relative_to(ROOT).as_posix()
        for d in ASSET_DIRS
        for f in sorted((ROOT / d).rglob("*"))
        if f.is_file() and f.relative_to(ROOT).as_posix() not in refs
    ]
    assert unused == [], f"files in docs/data or docs/img that no page uses: {unused}"


def test_every_data_file_and_image_a_page_names_exists() -> None:
    missing = [f"{page}: {path}" for path, page in _referenced().items() if not (ROOT / path).exists()]
    assert missing == []


# --------------------------------------------------------------------------- the manual's size

GENERATED = {"messages.md", "performance.md"}


def test_the_manual_is_short() -> None:
    """docs/ is at most 12 pages and 4,000 lines, a hand-written page at most ~400, no dated heading."""
    import re

    pages = sorted((ROOT / "docs").rglob("*.md"))
    lines = {
        p.relative_to(ROOT / "docs").as_posix(): len(p.read_text(encoding="utf-8").splitlines())
        for p in pages
    }
    assert len(pages) <= 12, sorted(lines)
    assert sum(lines.values()) <= 4000, lines
    long = {name: n for name, n in lines.items() if name not in GENERATED and n > 420}
    assert long == {}, f"pages over ~400 lines: {long}"
    dated = [
        f"{p.name}: {line}"
        for p in pages
        for line in p.read_text(encoding="utf-8").splitlines()
        if line.startswith("#") and re.search(r"\b20\d\d-\d\d-\d\d\b", line)
    ]
    assert dated == [], f"dated headings (a run log, not a manual): {dated}"
