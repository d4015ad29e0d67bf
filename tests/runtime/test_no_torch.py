"""stg_runtime never imports torch: import and render in a process where torch cannot be imported."""
import subprocess
import sys

CODE = r"""
import sys
class BlockTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch.") or name == "onnx" or name.startswith("onnx."):
            raise ImportError(f"{name} is blocked in this test")
        return None
sys.meta_path.insert(0, BlockTorch())
import stg_runtime
from stg_runtime import Player
from stg_runtime.demo import demo_model
from stg_runtime.cli import main
player = Player(demo_model("full", num_frames=4))
img = player.render(player.cameras[0].resized(32, 24), t=0.05)
assert img.shape == (24, 32, 3) and img.max() > 0
assert "torch" not in sys.modules and "onnx" not in sys.modules
print("ok")
"""


def test_runtime_imports_and_renders_without_torch():
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


TELEMETRY = r"""
import os, sys, warnings
os.environ.pop("ORT_DISABLE_TELEMETRY", None)
if sys.argv[1] == "after":
    import onnxruntime  # noqa: F401
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    import stg_runtime  # noqa: F401
print(os.environ.get("ORT_DISABLE_TELEMETRY"), len([w for w in caught if "ORT_DISABLE_TELEMETRY" in str(w.message)]))
"""


def test_importing_the_runtime_turns_onnxruntime_telemetry_off():
    """onnxruntime reads ORT_DISABLE_TELEMETRY when it is first imported (docs/security.md)."""
    first = subprocess.run([sys.executable, "-c", TELEMETRY, "first"], capture_output=True, text=True, timeout=300)
    assert first.stdout.split() == ["1", "0"], first.stderr
    after = subprocess.run([sys.executable, "-c", TELEMETRY, "after"], capture_output=True, text=True, timeout=300)
    assert after.stdout.split() == ["1", "1"], after.stderr  # too late for onnxruntime: a warning says so
