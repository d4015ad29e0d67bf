"""Every command as a newcomer meets it (tests/cli/cases.py lists the cases and says how to add one).

Each case runs the command's main() in this process and must end in one of two ways:
- success: exit code 0 and every output it promises;
- refusal: exit code 2, exactly one line on stderr, `PROG: error: ...`, naming the option or file and
  the problem (the case's regex), no traceback, and nothing written where the output would have gone.
An exception escaping main() (a traceback for the user) fails the case.
"""
import importlib
import inspect
import re
from pathlib import Path
from unittest import mock

import pytest

from .cases import all_cases

MAINS = {"stg-train": "stg_train.cli.train", "stg-eval": "stg_train.cli.eval", "stg-synth": "stg_train.cli.synth",
         "stg-convert": "stg_train.cli.convert", "stg-render": "stg_runtime.cli", "stg-view": "stg_runtime.viewer.cli"}

#: What a stand-in of the training pipeline returns (the figures the command prints).
FAKE_METRICS = {"heldout": {"psnr": 30.0, "ssim": 0.9, "dssim1": 0.05, "dssim2": 0.03, "fps": 100.0, "images": 4,
                            "cameras": ["cam00"]}, "file_bytes": 1000, "gaussians": 100}

CASES = all_cases()


def _stand_ins(monkeypatch) -> list:
    """Replace the library calls that train or serve by mocks with the real signatures (autospec: a
    call the real function would refuse raises TypeError here too); returns the mocks."""
    targets = [("stg_train.pipeline", "train"), ("stg_train.pipeline", "run_demo"),
               ("stg_train.distributed.run", "train_parallel"), ("stg_runtime.viewer.server", "serve")]
    mocks = []
    for module_name, name in targets:
        module = importlib.import_module(module_name)
        stand_in = mock.create_autospec(getattr(module, name), return_value=None if name == "serve" else FAKE_METRICS)
        monkeypatch.setattr(module, name, stand_in)
        mocks.append(stand_in)
    return mocks


def _fill(text: str, inputs: dict, out: Path) -> str:
    return text.format(**inputs, out=out)


def run_main(prog: str, argv: list[str]) -> int:
    main = importlib.import_module(MAINS[prog]).main
    try:
        return main(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_case(case, inputs, tmp_path, capsys, monkeypatch):
    mocks = _stand_ins(monkeypatch) if case.validate else []
    out = tmp_path / "fresh" / "out"
    out.parent.mkdir()
    argv = [_fill(a, inputs, out) for a in case.argv]
    rc = run_main(case.prog, argv)
    captured = capsys.readouterr()
    err_lines = [line for line in captured.err.splitlines() if line.strip() and not line.startswith("\r")]
    if case.expect == "ok":
        assert rc == 0, f"{case.id}: exit {rc}\n{captured.err[-2000:]}"
        for path in case.outputs:
            assert Path(_fill(path, inputs, out)).exists(), f"{case.id}: {path} was not written"
        if case.validate and case.prog == "stg-train":
            assert sum(m.call_count for m in mocks) == 1, "the pipeline was not called exactly once"
    else:
        assert rc == 2, f"{case.id}: exit {rc} (expected 2)\n{captured.err[-2000:]}"
        assert "Traceback" not in captured.err
        assert len(err_lines) == 1, f"{case.id}: expected one line on stderr, got:\n{captured.err[-2000:]}"
        line = err_lines[0]
        assert re.match(rf"^{case.prog}( [a-z0-9-]+)?: error: ", line), line
        assert re.search(case.names, line), f"{case.id}: the error does not name {case.names!r}: {line}"
        assert list(out.parent.iterdir()) == [], f"{case.id}: left {sorted(out.parent.rglob('*'))}"
        assert not any(m.called for m in mocks), "a refused case reached the pipeline"


def test_the_matrix_is_complete():
    """Every option of every command appears in some case (a new option must be added to cases.py)."""
    from stg_runtime.cli import build_parser as render_parser
    from stg_runtime.viewer.cli import build_parser as view_parser
    from stg_train.cli.convert import build_parser as convert_parser
    from stg_train.cli.eval import build_parser as eval_parser
    from stg_train.cli.synth import build_parser as synth_parser
    from stg_train.cli.train import build_parser as train_parser

    parsers = {"stg-train": train_parser(), "stg-eval": eval_parser(), "stg-synth": synth_parser(),
               "stg-render": render_parser(), "stg-view": view_parser()}
    sub = next(a for a in convert_parser()._actions if a.dest == "command")
    for name, parser in sub.choices.items():
        parsers[f"stg-convert {name}"] = parser
    missing = []
    for key, parser in parsers.items():
        prog, _, subcommand = key.partition(" ")
        used = {arg for c in CASES if c.prog == prog and (not subcommand or c.argv[:1] == (subcommand,))
                for arg in c.argv}
        for action in parser._actions:
            flags = [s for s in action.option_strings if s not in ("-h", "--help")]
            if flags and not any(f in used or f.replace("--", "--no-") in used for f in flags):
                missing.append(f"{key} {flags[0]}")
    assert missing == []


def test_case_count():
    """The size of the matrix (reported in the issue's note); it only grows."""
    assert len(CASES) >= 600, len(CASES)


def test_stand_ins_keep_the_signatures():
    """The stand-ins refuse what the real functions refuse (stg-train --ray --viewer once passed a
    keyword train_parallel does not take)."""
    from stg_train.distributed.run import train_parallel

    stand_in = mock.create_autospec(train_parallel)
    with pytest.raises(TypeError):
        stand_in(None, None, None, segment_frames=50, callback=None)
    assert "callback" not in inspect.signature(train_parallel).parameters
