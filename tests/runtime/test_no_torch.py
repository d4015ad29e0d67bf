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
