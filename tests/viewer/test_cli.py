"""stg-view's errors: a missing or corrupt model, a port in use, --device cuda without a GPU: one line
naming the problem, exit code 2, no traceback."""
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("viser")

from stg_runtime.viewer.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "formats" / "vectors" / "lite.stg"


def test_missing_model(tmp_path, capsys):
    assert main([str(tmp_path / "nothing.stg")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("stg-view: error:") and "nothing.stg" in err


def test_corrupt_model_in_a_subprocess(tmp_path):
    bad = tmp_path / "bad.stg"
    bad.write_bytes(MODEL.read_bytes()[:200])
    out = subprocess.run([sys.executable, "-m", "stg_runtime.viewer.cli", str(bad), "--port", "0"],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 2
    assert out.stderr.startswith("stg-view: error:") and "bad.stg" in out.stderr
    assert "Traceback" not in out.stderr


def test_port_in_use(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main([str(MODEL), "--port", str(port), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert f"port {port}" in err and "in use" in err


def test_cuda_without_a_gpu(capsys):
    from stg_runtime.cuda import device
    if device.usable():
        pytest.skip("numba sees a GPU (or its simulator) here")
    assert main([str(MODEL), "--device", "cuda"]) == 2
    assert "no CUDA GPU" in capsys.readouterr().err
