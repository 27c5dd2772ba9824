"""Documentation that is generated from code stays current."""

from __future__ import annotations

from pathlib import Path

from appliance.config.reference import configuration_reference

REPO = Path(__file__).resolve().parents[1]


def test_configuration_reference_is_current() -> None:
    committed = (REPO / "docs" / "configuration.md").read_text()
    assert committed == configuration_reference(), (
        "docs/configuration.md is stale: regenerate it with "
        "python -c 'from appliance.config.reference import configuration_reference as r; "
        "open(\"docs/configuration.md\",\"w\").write(r())'"
    )


def test_readme_opens_with_the_two_commands() -> None:
    text = (REPO / "README.md").read_text()
    block = text.split("```bash", 1)[1].split("```", 1)[0]
    assert [line.split()[0] for line in block.strip().splitlines()] == ["scripts/run", "scripts/test"]
    assert "scripts/test" in (REPO / ".ci" / "run").read_text()
