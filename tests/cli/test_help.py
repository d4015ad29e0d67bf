"""--help and argument errors: they import nothing heavy (bench/cli_help.py times them), the defaults
the help states are the parser's, and every option a message or help names exists."""
import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = {"stg-train": "stg_train.cli.train", "stg-eval": "stg_train.cli.eval", "stg-synth": "stg_train.cli.synth",
           "stg-prep": "stg_train.cli.prep",
           "stg-convert": "stg_train.cli.convert", "stg-render": "stg_runtime.cli", "stg-view": "stg_runtime.viewer.cli"}
#: What --help must not wait for.
HEAVY = ("torch", "numba", "onnxruntime", "cv2", "pycolmap", "viser", "ray", "av", "skimage", "scipy", "onnx")
#: A bad argument of each command (answered by the parser).
BAD = {"stg-train": ["DATA", "--out", "o", "--iterations", "0"], "stg-eval": ["m.stg"],
       "stg-synth": ["out", "--cameras", "x"],
       "stg-prep": ["videos", "out", "--offsets", "x"], "stg-convert": ["compress", "a.stg"],
       "stg-render": ["m.stg", "--out", "o.mp4", "--size", "x"], "stg-view": ["m.stg", "--port", "x"]}


def _modules_after(prog: str, argv: list[str]) -> tuple[int, list[str]]:
    code = (f"import sys, json\nfrom {MODULES[prog]} import main\n"
            f"try:\n    code = main({argv!r})\nexcept SystemExit as e:\n    code = e.code\n"
            "print(json.dumps([code, sorted(sys.modules)]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    code, modules = json.loads(out.stdout.strip().splitlines()[-1])
    return code, [m for m in modules if m.split(".")[0] in HEAVY]


@pytest.mark.parametrize("prog", sorted(MODULES))
def test_help_and_argument_errors_import_nothing_heavy(prog):
    assert _modules_after(prog, ["--help"]) == (0, [])
    assert _modules_after(prog, BAD[prog]) == (2, [])


def _parsers() -> dict:
    import importlib

    parsers = {prog: importlib.import_module(module).build_parser() for prog, module in MODULES.items()}
    sub = next(a for a in parsers["stg-convert"]._actions if a.dest == "command")
    for name, parser in sub.choices.items():
        parsers[f"stg-convert {name}"] = parser
    return parsers


def _effective_defaults() -> dict:
    """(command, option) -> the value an option left at None stands for, where its help states it."""
    from stg_train.config import TrainConfig

    d = TrainConfig()
    return {("stg-train", "--iterations"): d.iterations, ("stg-train", "--points"): d.num_points,
            ("stg-render", "--camera"): 0}


def _same(stated: str, value) -> bool:
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return stated == f"{value[0]}x{value[1]}"
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    if re.fullmatch(r"\d+x\d+", stated) and isinstance(value, int):  # a size given in pixels
        w, h = map(int, stated.split("x"))
        return w * h == value
    try:
        return float(stated) == float(value)
    except (TypeError, ValueError):
        return stated == str(value)


def test_the_defaults_in_the_help_are_the_parsers():
    effective = _effective_defaults()
    wrong, checked = [], 0
    for prog, parser in _parsers().items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.help or not action.option_strings:
                continue
            match = re.search(r"\(default:? ([\w.x-]+)(?=[),;:])", formatter._expand_help(action))
            if not match:
                continue
            stated, option = match.group(1), action.option_strings[-1]
            value = action.const if action.nargs == "?" and action.default is None else action.default
            if value is None:
                value = effective.get((prog.split()[0], option))
                if value is None:
                    if re.fullmatch(r"[\d.]+", stated):
                        wrong.append(f"{prog} {option}: help says {stated}, the parser has None")
                    continue  # a default described in words ("the camera's", "all")
            checked += 1
            if not _same(stated, value):
                wrong.append(f"{prog} {option}: help says {stated}, the parser has {value!r}")
    assert wrong == []
    assert checked >= 30


def _string_constants(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.value


def test_every_option_a_message_names_exists():
    """Hints in messages and help ("add --device cuda", "choose another with --port N") name options
    that some command has."""
    options = {o for p in _parsers().values() for a in p._actions for o in a.option_strings}
    unknown = {}
    for path in sorted([*ROOT.glob("stg_train/**/*.py"), *ROOT.glob("stg_runtime/**/*.py")]):
        for text in _string_constants(path):
            for option in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text):
                if option not in options and option.replace("--no-", "--") not in options:
                    unknown.setdefault(option, set()).add(str(path.relative_to(ROOT)))
    assert unknown == {}
