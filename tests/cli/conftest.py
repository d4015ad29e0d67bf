"""The tiny inputs of the command-line tests: one session-wide set of files that every case names by
placeholder ({data}, {model}, {path}, ...; see `inputs`)."""
import json
import socket
from pathlib import Path

import numpy as np
import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _n3v(root: Path, cameras: int, frames: int = 4, size=(32, 24)) -> Path:
    from stg_train.synthetic import SyntheticScene, write_n3v

    write_n3v(root, SyntheticScene(seed=0, duration=frames / 30.0), num_cameras=cameras, num_frames=frames, fps=30.0,
              width=size[0], height=size[1])
    return root


def _trained_model(data: Path, out: Path) -> Path:
    """A model trained for 2 steps on `data` through the real pipeline (its cameras are data's)."""
    from stg_train.data import load_dataset
    from stg_train.pipeline import train
    from stg_train.trainer import TrainConfig

    config = TrainConfig(model="lite", iterations=2, num_points=100, init="volume", motion_init="zero")
    train(load_dataset(data, show_progress=False), out, config, quiet=True, check=False, lpips={})
    return out / "model.stg"


@pytest.fixture(scope="session")
def inputs(tmp_path_factory) -> dict:
    """Placeholder -> path (str) of the shared inputs:

    data       an N3V scene: 3 cameras (cam00 held out) x 4 frames, 32x24
    other      another N3V scene, 4 cameras (a model of data does not fit it)
    one_cam    an N3V scene of one camera (nothing to train on)
    model      a lite model trained 2 steps on data (4 frames at 30 fps, data's 3 cameras)
    path       a camera path of 4 cameras (one per frame of model), 32x24
    path_long  the same path repeated: 8 cameras, more than the model's frames
    path_one   a camera path of 1 camera
    ply        a 3DGS PLY (the model's snapshot)
    empty      an empty file; text: a text file; folder: an empty folder; missing: a path that is not there
    path_NAME  a camera path whose camera 1 has the fault NAME of bad_camera_paths
    """
    from stg_runtime import format as stg_format
    from stg_runtime.camera import Camera, save_camera_path
    from stg_train.convert.gaussians3d import export_ply

    root = tmp_path_factory.mktemp("cli_inputs")
    data = _n3v(root / "data", 3)
    model = _trained_model(data, root / "run")
    cams = stg_format.load(model).cameras
    path = [Camera.look_at(cams[0].center + [0.05 * k, 0, 0], cams[0].center + 5 * cams[0].R[2], -cams[0].R[1], 50,
                           32, 24, name=f"p{k}") for k in range(4)]
    save_camera_path(root / "path.json", path)
    save_camera_path(root / "path_long.json", path + path)
    save_camera_path(root / "path_one.json", path[:1])
    export_ply(stg_format.load(model), root / "snapshot.ply", 0.0)
    (root / "empty").write_bytes(b"")
    (root / "text.txt").write_text("not a model\n")
    (root / "folder").mkdir()
    bad_paths = {f"path_{name}": path for name, (path, _) in bad_camera_paths(root).items()}
    return {**bad_paths, "data": str(data), "other": str(_n3v(root / "other", 4)), "one_cam": str(_n3v(root / "one_cam", 1)),
            "model": str(model), "path": str(root / "path.json"), "path_long": str(root / "path_long.json"),
            "path_one": str(root / "path_one.json"), "ply": str(root / "snapshot.ply"), "empty": str(root / "empty"),
            "text": str(root / "text.txt"), "folder": str(root / "folder"), "missing": str(root / "missing"),
            "port": str(free_port()), "root": str(root)}


def bad_camera_paths(folder: Path) -> dict:
    """name -> (path of a camera-path file with one fault in camera 1, the field its error must name)."""
    from stg_runtime.camera import Camera

    good = Camera.look_at([0, 0, 0], [0, 0, 5], [0, -1, 0], 50, 32, 24).to_dict()
    scaled = np.asarray(good["world_to_camera"], dtype=np.float64).reshape(4, 4)
    scaled[:3, :3] *= 2  # a scaled rotation: not a camera pose
    faults = {"no_fx": ({k: v for k, v in good.items() if k != "fx"}, "fx"),
              "fx_text": ({**good, "fx": "abc"}, "fx"),
              "width_text": ({**good, "width": "160"}, "width"),
              "width_zero": ({**good, "width": 0}, "width"),
              "w2c_12": ({**good, "world_to_camera": good["world_to_camera"][:12]}, "world_to_camera"),
              "w2c_scaled": ({**good, "world_to_camera": scaled.ravel().tolist()}, "world_to_camera"),
              "w2c_text": ({**good, "world_to_camera": "identity"}, "world_to_camera"),
              "not_object": ("camera", "camera object"),
              "fisheye_no_k": ({**{k: v for k, v in good.items() if k not in ("fx", "fy", "cx", "cy")},
                                "model": "fisheye", "intrinsics": {"fx": 20, "fy": 20, "cx": 16, "cy": 12}}, "k1")}
    out = {}
    for name, (entry, field) in faults.items():
        (folder / f"{name}.json").write_text(json.dumps([good, entry]))
        out[name] = (str(folder / f"{name}.json"), field)
    return out
