"""A moderate fuzz run in CI (tools/fuzz.py: a few thousand mutated .stg files and PLYs, checksums
recomputed): loading raises only FormatError, rendering only RenderError, the PLY readers only PLYError.
docs/security.md has the figures of longer runs."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_mutated_files_raise_only_the_documented_errors():
    out = subprocess.run([sys.executable, str(ROOT / "tools" / "fuzz.py"), "--stg", "3000", "--ply", "3000",
                          "--seed", "7"], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert lines[-1] == "unexpected: 0"
    counts = {line.split(None, 1)[1]: int(line.split(None, 1)[0]) for line in lines[1:-1] if line.split()[0].isdigit()}
    # the run reached every stage: files refused at load, files that load and render, PLYs read and refused
    assert counts.get("stg: loads and renders", 0) > 100
    assert sum(n for k, n in counts.items() if k.startswith("stg: FormatError")) > 1000
    assert sum(n for k, n in counts.items() if k.startswith("ply: PLYError")) > 1000
