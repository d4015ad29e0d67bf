"""The import contract of the two packages (the architecture in docs/architecture.md):

- no import cycle between project modules, imports inside functions included;
- stg_runtime never imports torch, onnx or stg_train;
- optional backends stay in their own module: gsplat only in stg_train.render.gsplat_backend, CuPy only
  in stg_runtime.cuda.device, Ray only in stg_train.distributed.ray_cluster, viser only in
  stg_runtime.viewer.server;
- the rig's modelling (stg_train.rig) sits below the loop: it imports no trainer, strategy, splatter,
  pipeline or command line, and only the trainer builds a CameraRig;
- Player(device="cpu") renders without importing numba.cuda, torch, onnx or the viewer (viser).
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("stg_runtime", "stg_train")


def _modules() -> dict[str, Path]:
    """Module name -> file, for every module of the packages."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


MODULES = _modules()


def _imports(name: str) -> list[tuple[str, int]]:
    """(absolute module imported, line) for every import statement in module `name`, at any depth.
    `from package import x` counts as importing package.x when that is a module, else package."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                origin = ".".join(base + ([node.module] if node.module else []))
            else:
                origin = node.module
            for alias in node.names:
                full = f"{origin}.{alias.name}"
                out.append((full if full in MODULES else origin, node.lineno))
    return out


def _graph() -> dict[str, set[str]]:
    return {name: {m for m, _ in _imports(name) if m in MODULES and m != name} for name in MODULES}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, result = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                result.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return result


def test_the_checker_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_the_graph_sees_imports_inside_functions():
    assert "stg_runtime.cuda.decoder" in _graph()["stg_runtime.player"]  # imported in Player._render_cuda


def _offenders(names, where) -> list[str]:
    return [f"{module}:{line} imports {imported}" for module in MODULES if where(module)
            for imported, line in _imports(module) if imported.split(".")[0] in names]


def test_runtime_never_imports_torch_onnx_or_the_trainer():
    assert _offenders({"torch", "onnx", "stg_train"}, lambda m: m.startswith("stg_runtime")) == []


def test_optional_backends_stay_in_their_modules():
    assert _offenders({"gsplat"}, lambda m: m != "stg_train.render.gsplat_backend") == []
    assert _offenders({"cupy"}, lambda m: m != "stg_runtime.cuda.device") == []
    assert _offenders({"ray"}, lambda m: m != "stg_train.distributed.ray_cluster") == []
    assert _offenders({"viser"}, lambda m: m != "stg_runtime.viewer.server") == []


#: What stg_train.rig may import of stg_train: its own modules and the layers below the training loop.
RIG_MAY_IMPORT = ("stg_train.rig", "stg_train.data", "stg_train.config", "stg_train.metrics", "stg_train.rotations")


def test_the_rig_sits_below_the_training_loop():
    above = [f"{module}:{line} imports {imported}" for module in MODULES if module.startswith("stg_train.rig")
             for imported, line in _imports(module)
             if imported.startswith("stg_train") and not imported.startswith(RIG_MAY_IMPORT)]
    assert above == []
    builders = {m for m in MODULES if "stg_train.rig.camera_rig" in _graph()[m]} - {"stg_train.rig"}
    assert builders == {"stg_train.trainer"}


CPU_PLAYER = r"""
import sys
from stg_runtime import Player
from stg_runtime.demo import demo_model
player = Player(demo_model("full", num_frames=4), device="cpu")
image = player.render(player.cameras[0].resized(32, 24), t=0.05)
assert image.shape == (24, 32, 3) and image.max() > 0
print(sorted(m for m in ("numba.cuda", "torch", "onnx", "stg_train", "viser", "stg_runtime.viewer")
             if m in sys.modules))
"""


def test_cpu_player_imports_no_gpu_code_torch_or_trainer():
    out = subprocess.run([sys.executable, "-c", CPU_PLAYER], capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
