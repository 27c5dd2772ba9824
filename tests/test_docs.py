"""Documentation that is generated from code stays current."""

from __future__ import annotations

import os
import re
import subprocess
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


def _readme_commands() -> list[str]:
    """The ``scan3d ...`` commands of the README's command table, placeholders filled with sample values."""
    text = (REPO / "README.md").read_text()
    table = text.split("## Commands", 1)[1].split("\n## ", 1)[0]
    fill = {"FILE": "f.yaml", "DIR": "d", "OUT.ply": "o.ply", "OUT": "o", "R.json": "r.json", "PAGE": "p.html",
            "N": "2", "PORT": "/dev/ttyACM0", "ADDR": "127.0.0.1", "NAME": "cam0", "MANIFEST": "m.yaml",
            "IMAGE": "i.png"}
    out = []
    for cell in re.findall(r"^\| (.*?) \| [^|]", table, re.M):
        for cmd in re.findall(r"`(scan3d [^`]*)`", cell):
            cmd = re.sub(r"\[([^]]*)\]", r"\1", cmd).replace("--board ...", "--board chessboard")  # optional parts too
            cmd = re.sub(r"(\S+)\\\|\S+", r"\1", cmd).replace("...", "")  # the first of A|B
            cmd = re.sub(r"--mode M", "--mode both", cmd)
            cmd = re.sub(r"--model M", "--model standard", cmd)
            out.append(" ".join(fill.get(w, w) for w in cmd.split()))
    return out


def test_every_readme_command_is_accepted_by_the_command_line() -> None:
    from appliance.cli import build_parser

    commands = _readme_commands()
    assert len(commands) >= 15, commands
    parser = build_parser()
    for cmd in commands:
        try:
            args = parser.parse_args(cmd.split()[1:])
        except SystemExit:
            raise AssertionError(f"README command not accepted by scan3d: {cmd}") from None
        assert callable(args.func), cmd


def test_readme_first_commands_are_runnable_scripts() -> None:
    """The two commands the README opens with exist, are executable shell scripts, and CI runs the test one."""
    text = (REPO / "README.md").read_text()
    block = text.split("```bash", 1)[1].split("```", 1)[0]
    scripts = [line.split()[0] for line in block.strip().splitlines()]
    assert scripts == ["scripts/run", "scripts/test"]
    for script in scripts:
        path = REPO / script
        assert path.is_file() and os.access(path, os.X_OK), f"{script}: missing or not executable"
        r = subprocess.run(["bash", "-n", str(path)], capture_output=True, text=True, timeout=30, check=False)
        assert r.returncode == 0, f"{script}: {r.stderr}"
    ci = subprocess.run(["bash", "-x", "-n", str(REPO / ".ci" / "run")], capture_output=True, text=True,
                        timeout=30, check=False)
    assert ci.returncode == 0 and "exec scripts/test" in (REPO / ".ci" / "run").read_text()


def test_relative_links_in_the_docs_lead_somewhere() -> None:
    """Every relative link of README.md and docs/*.md names a file or folder of the repository."""
    broken = []
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (doc.parent / target.split("#", 1)[0]).exists():
                broken.append(f"{doc.relative_to(REPO)}: {target}")
    assert not broken, "broken links:\n" + "\n".join(broken)
