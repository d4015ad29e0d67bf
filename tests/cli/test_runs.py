"""stg-train where a combination must really run (a few steps on the tiny scene of conftest.py): reruns
into a used folder, settings under --resume, Ctrl-C, the training viewer, segments."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stg_train.cli.train import main as train_main

from .conftest import free_port

FAST = ["--model", "lite", "--points", "100", "--init", "volume", "--motion-init", "zero", "--quiet", "--no-check"]
ROOT = Path(__file__).resolve().parents[2]


def _interruptible() -> None:
    """In the child: Ctrl-C as in a terminal, whatever the test process inherited or blocked."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run(argv, capsys):
    rc = train_main([str(a) for a in argv])
    captured = capsys.readouterr()
    return rc, captured.err


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("stg-train: error: "), err
    return lines[0]


def test_a_rerun_into_a_used_folder_is_refused_with_the_choices(inputs, tmp_path, capsys):
    out = tmp_path / "run"
    assert run([inputs["data"], "--out", out, "--iterations", "2", *FAST], capsys)[0] == 0
    assert {"checkpoint.pt", "model.stg", "metrics.json"} <= {p.name for p in out.iterdir()}
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    rc, err = run([inputs["data"], "--out", out, "--iterations", "2", *FAST], capsys)
    line = one_error_line(err)
    assert rc == 2 and "finished run" in line and "--resume" in line and "--out" in line and "--force" in line
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before  # nothing overwritten
    (out / "model.stg").unlink()
    (out / "metrics.json").unlink()  # a partial run: a checkpoint only
    rc, err = run([inputs["data"], "--out", out, "--iterations", "2", *FAST], capsys)
    assert rc == 2 and "unfinished run" in one_error_line(err)
    assert run([inputs["data"], "--out", out, "--iterations", "2", "--force", *FAST], capsys)[0] == 0
    assert (out / "model.stg").exists()


def test_resume_applies_what_may_change_and_refuses_the_rest(inputs, tmp_path, capsys):
    out = tmp_path / "run"
    assert run([inputs["data"], "--out", out, "--iterations", "2", *FAST], capsys)[0] == 0
    fast = [a for a in FAST if a != "--quiet"]
    rc, err = run([inputs["data"], "--out", out, "--resume", "--iterations", "4", "--checkpoint-every", "1",
                   "--threads", "1", *fast], capsys)
    assert rc == 0, err
    assert "--threads 1 applies to the resumed run" in err
    assert "at step 2 of 4" in err and "--iterations 4 replaces the checkpoint's 2" in err
    assert "--checkpoint-every 1 replaces the checkpoint's" in err
    assert json.loads((out / "metrics.json").read_text())["iterations"] == 4
    for option, value, field in (("--batch", "1", "batch"), ("--model", "full", "model"), ("--seed", "3", "seed"),
                                 ("--init", "sfm", "init"), ("--points", "70", "num_points")):
        args = [a for a in fast if a not in (option,)]
        if option in fast:
            i = fast.index(option)
            args = fast[:i] + fast[i + 2:]
        rc, err = run([inputs["data"], "--out", out, "--resume", option, value, *args], capsys)
        line = one_error_line(err)
        assert rc == 2 and option in line and field in line and "--force" in line, line
    rc, err = run([inputs["data"], "--out", out, "--resume", *fast], capsys)  # finished: no empty bar
    assert rc == 0 and "is finished (step 4 of 4)" in err and "train [" not in err
    rc, err = run([inputs["data"], "--out", out, "--resume", "--iterations", "3", *FAST], capsys)
    assert rc == 2 and "already at step 4" in one_error_line(err)


def test_a_short_run_leaves_a_checkpoint_to_resume(inputs, tmp_path, capsys):
    """A run shorter than --checkpoint-every still writes its checkpoint (at the end), so --resume
    continues it instead of starting again."""
    out = tmp_path / "run"
    assert run([inputs["data"], "--out", out, "--iterations", "3", "--checkpoint-every", "500", *FAST], capsys)[0] == 0
    rc, err = run([inputs["data"], "--out", out, "--resume", "--iterations", "5", *[a for a in FAST if a != "--quiet"]],
                  capsys)
    assert rc == 0 and "resuming" in err and "at step 3 of 5" in err


def test_ctrl_c_saves_a_checkpoint_and_prints_one_resume_line(inputs, tmp_path):
    """Ctrl-C in the middle of a run (far from any periodic checkpoint): the checkpoint is saved, one
    line says how to resume, no traceback; resuming continues from that step."""
    out = tmp_path / "run"
    verbose = [a for a in FAST if a != "--quiet"]
    argv = [inputs["data"], "--out", str(out), "--iterations", "100000", "--checkpoint-every", "100000", *verbose]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "stg_train.cli.train", *argv], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_interruptible)
    seen = []
    for line in proc.stderr:  # the initial points are reported just before the first step
        seen.append(line)
        if "initial points" in line:
            break
    time.sleep(3)
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=240)
    err = "".join(seen) + rest
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    lines = [line for line in err.splitlines() if "interrupted" in line]
    assert len(lines) == 1 and lines[0].endswith("--resume") and "saved" in lines[0], err
    step = int(lines[0].split("interrupted at step ")[1].split()[0])
    assert step >= 1 and (out / "checkpoint.pt").exists()
    resumed = subprocess.run([sys.executable, "-m", "stg_train.cli.train", inputs["data"], "--out", str(out),
                              "--resume", "--iterations", str(step + 2), *verbose],
                             cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    assert resumed.returncode == 0, resumed.stderr
    assert f"at step {step} of {step + 2}" in resumed.stderr


def test_the_training_viewer_runs_with_a_real_run(inputs, tmp_path, capsys):
    pytest.importorskip("viser")
    out = tmp_path / "run"
    rc, err = run([inputs["data"], "--out", out, "--iterations", "3", "--viewer", str(free_port()), *FAST], capsys)
    assert rc == 0, err
    assert (out / "model.stg").exists()


def test_segments_run_and_merge(inputs, tmp_path, capsys):
    out = tmp_path / "run"
    rc, err = run([inputs["data"], "--out", out, "--iterations", "2", "--segment-frames", "2", *FAST], capsys)
    assert rc == 0, err
    assert (out / "segments" / "00" / "model.stg").exists() and (out / "segments" / "01" / "model.stg").exists()
    assert (out / "model.stg").exists()
    rc, err = run([inputs["data"], "--out", out, "--iterations", "2", "--segment-frames", "2", "--segments", "1", *FAST],
                  capsys)
    assert rc == 2 and "segments/01" in one_error_line(err)
