"""The README and the docs: the set-up and test commands are what CI runs; the README stays short and
the links resolve; the Python snippets run as written (or say why not), every stg-* command line
parses, the camera-path JSON examples load."""
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _command_after(heading: str, text: str) -> str:
    section = text.split(f"## {heading}", 1)[1]
    return re.search(r"```bash\n(.+?)\n```", section, re.S).group(1).strip()


def test_ci_runs_the_readme_commands():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    for line in _command_after("Set up", readme).splitlines():
        assert line in ci
    assert _command_after("Test", readme) in ci


def test_readme_stays_short_and_links_resolve():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    missing = []
    for page in pages:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target and not (page.parent / target).exists():
                missing.append(f"{page.relative_to(ROOT)} -> {target}")
    assert missing == []
    linked = set(re.findall(r"\(docs/([\w-]+\.md)\)", readme))
    assert linked == {p.name for p in (ROOT / "docs").glob("*.md")}  # every page is reachable from the README


def _paragraphs(text: str) -> list[list[str]]:
    """The prose paragraphs of a markdown page: runs of non-blank lines outside code fences, each list
    item its own paragraph, tables and headings left out."""
    paragraphs, current, fenced = [], [], False
    for line in text.splitlines() + [""]:
        if line.startswith("```"):
            fenced = not fenced
            line = ""
        starts_item = re.match(r"\s*([-*]|\d+\.) ", line)
        if fenced or not line.strip() or line.startswith(("#", "|")) or starts_item:
            if current:
                paragraphs.append(current)
            current = [line] if starts_item and not fenced else []
            continue
        current.append(line)
    return paragraphs


def test_readme_paragraphs_stay_short():
    long = [p[0][:60] for p in _paragraphs((ROOT / "README.md").read_text()) if len(p) > 8]
    assert long == []


def test_paragraphs_are_split_as_markdown_shows_them():
    text = "one\ntwo\n\n- item\n  more\n- next\n\n```bash\na\nb\n```\n| t |\nlast\n"
    assert _paragraphs(text) == [["one", "two"], ["- item", "  more"], ["- next"], ["last"]]


def test_docs_pages_stay_reference_sized():
    """No docs page, notes included, over 400 lines (the format spec is the one long page)."""
    pages = [*(ROOT / "docs").glob("*.md"), *(ROOT / "docs" / "notes").glob("*.md")]
    long = {str(p.relative_to(ROOT)): n for p in pages if (n := len(p.read_text().splitlines())) > 400}
    assert long == {}


# -- the snippets run as written -------------------------------------------------------------------
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: Python snippets that do not run here, and why (page, index of the ```python block on the page).
NOT_RUN = {
    ("docs/datasets.md", 0): "a template: K, Rt, width and height are your calibration's",
    ("docs/distributed.md", 0): "trains 30000 steps on GPUs, on a Ray cluster",
    ("docs/training.md", 0): "trains 3000 steps (the same call runs in tests/train/test_pipeline.py)",
    ("docs/training.md", 1): "the two calls a strategy receives, not a program",
}
#: Snippets that need a GPU: run only where numba sees one.
NEEDS_GPU = {("docs/gpu.md", 0)}


def _blocks(page: Path, language: str) -> list[str]:
    return re.findall(rf"(?ms)^```{language}\n(.*?)^```", page.read_text())


def _python_snippets():
    for page in PAGES:
        for i, code in enumerate(_blocks(page, "python")):
            key = (str(page.relative_to(ROOT)), i)
            yield pytest.param(key, code, id=f"{key[0]}:{i}",
                               marks=[pytest.mark.skip(reason=NOT_RUN[key])] if key in NOT_RUN else [])


@pytest.fixture(scope="module")
def snippet_folder(tmp_path_factory):
    """A folder holding the files the snippets name: scene.stg, model.stg and huge.stg (a small model),
    point_cloud.ply (a 3DGS PLY)."""
    from stg_runtime import format as stg_format
    from stg_runtime.demo import demo_model
    from stg_train.convert.gaussians3d import export_ply

    folder = tmp_path_factory.mktemp("snippets")
    model = demo_model("full", num_frames=4)
    for name in ("scene.stg", "model.stg", "huge.stg"):
        stg_format.save(model, folder / name)
    export_ply(model, folder / "point_cloud.ply", 0.0)
    return folder


@pytest.mark.parametrize("key, code", list(_python_snippets()))
def test_python_snippets_run_as_written(key, code, snippet_folder):
    if key in NEEDS_GPU:
        from stg_runtime.cuda.device import gpu_available
        if not gpu_available():
            pytest.skip("needs an NVIDIA GPU")
    result = subprocess.run([sys.executable, "-c", code], cwd=snippet_folder, capture_output=True, text=True,
                            timeout=600, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert result.returncode == 0, f"{key}:\n{code}\n{result.stderr[-3000:]}"


def test_every_not_run_snippet_exists():
    keys = {(str(p.relative_to(ROOT)), i) for p in PAGES for i, _ in enumerate(_blocks(p, "python"))}
    assert set(NOT_RUN) | NEEDS_GPU <= keys


def _command_lines():
    """Every stg-* command line of the ```bash blocks (continuations joined, comments dropped)."""
    for page in PAGES:
        for block in _blocks(page, "bash"):
            for line in block.replace("\\\n", " ").splitlines():
                words = shlex.split(line, comments=True)
                if words and words[0].startswith("stg-"):
                    yield str(page.relative_to(ROOT)), words


def test_documented_command_lines_parse():
    """Every stg-* command line in the README and the docs is accepted by its command's parser (the
    options exist, the values are valid)."""
    import importlib

    modules = {"stg-train": "stg_train.cli.train", "stg-eval": "stg_train.cli.eval", "stg-synth": "stg_train.cli.synth",
               "stg-prep": "stg_train.cli.prep",
               "stg-convert": "stg_train.cli.convert", "stg-render": "stg_runtime.cli", "stg-view": "stg_runtime.viewer.cli"}
    bad, count = [], 0
    for page, words in _command_lines():
        parser = importlib.import_module(modules[words[0]]).build_parser()
        try:
            parser.parse_args(words[1:])
            count += 1
        except SystemExit:
            bad.append(f"{page}: {shlex.join(words)}")
    assert bad == []
    assert count >= 30


def test_json_examples_of_camera_paths_load(tmp_path):
    from stg_runtime.camera import load_camera_path

    blocks = _blocks(ROOT / "docs" / "render.md", "json")
    assert blocks
    for i, block in enumerate(blocks):
        (tmp_path / f"{i}.json").write_text(block)
        cameras = load_camera_path(tmp_path / f"{i}.json")
        assert len(cameras) == len(json.loads(block))
