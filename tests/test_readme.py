"""The README's set-up and test commands are what CI runs."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _command_after(heading: str, text: str) -> str:
    section = text.split(f"## {heading}", 1)[1]
    return re.search(r"```bash\n(.+?)\n```", section, re.S).group(1).strip()


def test_ci_runs_the_readme_commands():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert _command_after("Set up", readme) in ci
    assert _command_after("Test", readme) in ci
