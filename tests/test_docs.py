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
