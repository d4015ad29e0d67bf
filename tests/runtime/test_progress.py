"""stg_runtime.progress: the bars of work done in stages (written to a non-terminal stream: a line
per draw)."""
import io

import stg_runtime.progress as progress


def test_stages_draw_one_bar_each_in_turn_and_close_each(monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(progress.sys, "stderr", stream)
    with progress.progress_stages() as stage:
        first, second, silent = stage("structure from motion"), stage("initial motion"), stage("never")
        for k in (1, 2, 3):
            first(k, 3)
        assert "structure from motion" in stream.getvalue() and "initial motion" not in stream.getvalue()
        second(1, 2)
        second(2, 2)
    lines = stream.getvalue().splitlines()
    sfm = [i for i, line in enumerate(lines) if line.startswith("structure from motion")]
    motion = [i for i, line in enumerate(lines) if line.startswith("initial motion")]
    assert sfm and motion and max(sfm) < min(motion)  # the first bar is finished before the second draws
    assert "3/3" in lines[max(sfm)] and "2/2" in lines[max(motion)]
    assert not any(line.startswith("never") for line in lines)


def test_disabled_stages_draw_nothing(monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(progress.sys, "stderr", stream)
    with progress.progress_stages(enabled=False) as stage:
        stage("a")(1, 1)
        stage("b")(1, 1)
    assert stream.getvalue() == ""


def test_progress_callback_is_one_stage(monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(progress.sys, "stderr", stream)
    with progress.progress_callback("decode frames") as report:
        report(1, 2)
        report(2, 2)
    with progress.progress_callback("cached"):
        pass  # no report: no bar
    lines = stream.getvalue().splitlines()
    assert lines and all(line.startswith("decode frames") for line in lines) and "2/2" in lines[-1]
