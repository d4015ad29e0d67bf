"""`stg-convert` end to end on small files: every subcommand, --help, and clean failures."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stg_runtime import Model, Segment
from stg_runtime import format as stg_format
from stg_runtime.demo import random_model
from stg_train.cli.convert import main
from stg_train.convert.ply import read_ply, write_ply

ROOT = Path(__file__).resolve().parents[2]
COMMANDS = ["compress", "import-reference", "import-3dgs", "export-ply", "merge"]


def model_file(path, start_frame=0, kind="lite", n=300, seed=0) -> Path:
    m = random_model(n, kind, seed=seed, width=48, height=32)
    seg = m.segments[0]
    seg = Segment(start_frame, seg.num_frames, decoder=seg.decoder, activation=seg.activation, **seg.arrays())
    stg_format.save(Model(kind, m.fps, [seg], m.cameras), path)
    return Path(path)


def reference_ply(path, n=50, seed=0) -> Path:
    rng = np.random.default_rng(seed)
    names = (["x", "y", "z", "trbf_center", "trbf_scale", "nx", "ny", "nz"] + [f"motion_{i}" for i in range(9)]
             + [f"f_dc_{i}" for i in range(3)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
             + [f"rot_{i}" for i in range(4)] + [f"omega_{i}" for i in range(4)])
    props = {k: rng.normal(0, 0.3, n).astype(np.float32) for k in names}
    props["z"] += 5
    write_ply(path, props)
    return Path(path)


def gs_ply(path, n=40, seed=0) -> Path:
    rng = np.random.default_rng(seed)
    names = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(9)]
             + ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])
    props = {k: rng.normal(0, 0.3, n).astype(np.float32) for k in names}
    write_ply(path, props)
    return Path(path)


def run(argv, capsys):
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def only(folder: Path) -> set:
    return {p.name for p in folder.iterdir()}


def test_help_of_every_command(capsys):
    for argv in [["--help"]] + [[c, "--help"] for c in COMMANDS]:
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 0
        assert "usage: stg-convert" in capsys.readouterr().out
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "convert.py"), "--help"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0 and "import-reference" in done.stdout


def test_compress_prints_report_and_writes_a_smaller_file(tmp_path, capsys):
    src = model_file(tmp_path / "in.stg", kind="full", n=600)
    rc, out, err = run(["compress", src, tmp_path / "out.stg", "--preset", "small"], capsys)
    assert rc == 0, err
    assert "Gaussians: 600 ->" in out and "PSNR against the uncompressed render" in out and "features" in out
    assert (tmp_path / "out.stg").stat().st_size < 0.3 * src.stat().st_size
    rc, out, err = run(["compress", src, tmp_path / "fixed.stg", "--encoding", "position=f16,features=u8",
                        "--encoding", "scale=u16", "--order", "none", "--no-prune-unseen", "--prune-opacity", "0",
                        "--level", "1"], capsys)
    assert rc == 0, err
    assert "position        f16" in out and "features         u8" in out and "scale           u16" in out
    back = stg_format.load(tmp_path / "fixed.stg")
    assert back.segments[0].count == 600


def test_compress_with_a_dataset(tmp_path, capsys):
    from stg_train.synthetic import SyntheticScene, write_n3v

    write_n3v(tmp_path / "data", SyntheticScene(seed=0, duration=0.1), num_cameras=3, num_frames=3, fps=30,
              width=32, height=24)
    src = model_file(tmp_path / "in.stg", n=200)
    rc, out, err = run(["compress", src, tmp_path / "out.stg", "--data", tmp_path / "data"], capsys)
    assert rc == 0, err
    assert "(dataset)" in out and "PSNR against ground truth" in out and "change" in out


def test_import_reference_and_3dgs_and_export(tmp_path, capsys):
    plys = [reference_ply(tmp_path / "s0.ply", seed=0), reference_ply(tmp_path / "s1.ply", seed=1)]
    rc, out, err = run(["import-reference", *plys, tmp_path / "ref.stg", "--fps", "25", "--start-frame", "100",
                        "--segment-frames", "50,20"], capsys)
    assert rc == 0, err
    m = stg_format.load(tmp_path / "ref.stg")
    assert m.kind == "lite" and m.fps == 25 and [(s.start_frame, s.num_frames) for s in m.segments] == [(100, 50), (150, 20)]
    assert m.provenance["settings"]["duration"] == [50.0, 50.0]  # the official default
    rc, out, err = run(["import-reference", *plys, tmp_path / "own.stg", "--segment-frames", "50,20",
                        "--duration", "50,20"], capsys)
    assert rc == 0, err
    own = stg_format.load(tmp_path / "own.stg")
    assert own.provenance["settings"]["duration"] == [50.0, 20.0]
    assert np.array_equal(own.segments[0].position, m.segments[0].position)  # 50 frames at duration 50: the same
    assert not np.array_equal(own.segments[1].t_center, m.segments[1].t_center)  # rescaled by 20/50 or not
    with pytest.raises(SystemExit) as exit_code:
        run(["import-reference", *plys, tmp_path / "bad.stg", "--duration", "0"], capsys)
    assert exit_code.value.code == 2 and "durations must be positive" in capsys.readouterr().err

    rc, out, err = run(["import-3dgs", gs_ply(tmp_path / "gs.ply"), tmp_path / "gs.stg", "--fps", "24"], capsys)
    assert rc == 0, err
    g = stg_format.load(tmp_path / "gs.stg")
    assert g.kind == "sh" and g.segments[0].count == 40 and g.segments[0].channels == 12

    rc, out, err = run(["export-ply", tmp_path / "ref.stg", tmp_path / "snap.ply", "--time", "4.5"], capsys)
    assert rc == 0, err
    props, count = read_ply(tmp_path / "snap.ply")
    assert 0 < count <= 50 and {"x", "f_dc_0", "opacity", "rot_3"} <= set(props)


def test_merge(tmp_path, capsys):
    a = model_file(tmp_path / "a.stg", 0, seed=0)
    b = model_file(tmp_path / "b.stg", 50, seed=1)
    rc, out, err = run(["merge", a, b, tmp_path / "ab.stg"], capsys)
    assert rc == 0, err
    m = stg_format.load(tmp_path / "ab.stg")
    assert [s.start_frame for s in m.segments] == [0, 50] and m.num_frames == 100


@pytest.mark.parametrize("argv_of", [
    lambda d, bad: ["compress", bad, d / "out.stg"],
    lambda d, bad: ["export-ply", bad, d / "out.ply", "--time", "0"],
    lambda d, bad: ["merge", bad, model_file(d / "b.stg", 50), d / "out.stg"],
    lambda d, bad: ["import-reference", bad, d / "out.stg"],
    lambda d, bad: ["import-3dgs", bad, d / "out.stg"],
])
def test_missing_and_corrupt_inputs_fail_cleanly(tmp_path, capsys, argv_of):
    for name, content in (("missing.stg", None), ("corrupt.stg", b"\x89STG\r\n\x1a\n" + b"\x01" * 40),
                          ("corrupt.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n"
                                          b"property float x\nend_header\n\x00\x00")):
        bad = tmp_path / name
        if content is not None:
            bad.write_bytes(content)
        argv = argv_of(tmp_path, bad)
        before = only(tmp_path)
        rc, out, err = run(argv, capsys)
        assert rc == 2
        assert err.startswith(f"stg-convert: error: {bad}") and "Traceback" not in err, err
        assert only(tmp_path) == before  # no output, no temporary file left behind


def test_argument_errors(tmp_path, capsys):
    src = model_file(tmp_path / "in.stg")
    rc, out, err = run(["compress", src, tmp_path / "o.stg", "--encoding", "position=u12"], capsys)
    assert rc == 2 and "--encoding: bad encoding 'position=u12'" in err
    rc, out, err = run(["export-ply", src, tmp_path / "o.ply", "--time", "99"], capsys)
    assert rc == 2 and f"{src}: --time 99" in err
    ply = reference_ply(tmp_path / "r.ply")
    rc, out, err = run(["import-reference", ply, tmp_path / "o.stg", "--decoder", tmp_path / "d.pth"], capsys)
    assert rc == 2 and "no decoder" in err
    rc, out, err = run(["compress", src, tmp_path / "no" / "o.stg"], capsys)
    assert rc == 2 and f"{tmp_path / 'no' / 'o.stg'}: cannot write: the folder" in err
    with pytest.raises(SystemExit) as e:
        main(["merge", str(src)])
    assert e.value.code == 2
    assert not (tmp_path / "o.stg").exists() and not (tmp_path / "o.ply").exists()


NO_TORCH = r"""
import sys
class BlockTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"{name} is blocked in this test")
        return None
sys.meta_path.insert(0, BlockTorch())
from stg_train.cli.convert import main
rc = main(sys.argv[1:])
assert "torch" not in sys.modules
sys.exit(rc)
"""


def test_without_torch(tmp_path):
    src = model_file(tmp_path / "in.stg")
    done = subprocess.run([sys.executable, "-c", NO_TORCH, "compress", str(src), str(tmp_path / "out.stg")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rng = np.random.default_rng(0)
    names = (["x", "y", "z", "trbf_center", "trbf_scale", "nx", "ny", "nz"] + [f"motion_{i}" for i in range(9)]
             + [f"f_dc_{i}" for i in range(6)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
             + [f"rot_{i}" for i in range(4)] + [f"omega_{i}" for i in range(4)] + [f"f_t_{i}" for i in range(3)])
    write_ply(tmp_path / "full.ply", {k: rng.normal(0, 0.3, 20).astype(np.float32) for k in names})
    (tmp_path / "d.pth").write_bytes(b"")
    done = subprocess.run([sys.executable, "-c", NO_TORCH, "import-reference", str(tmp_path / "full.ply"),
                           str(tmp_path / "full.stg"), "--decoder", str(tmp_path / "d.pth")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert done.stderr.startswith(f"stg-convert: error: {tmp_path / 'd.pth'}: reading a decoder state dict needs torch")
    assert not (tmp_path / "full.stg").exists()
