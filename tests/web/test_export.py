"""`stg-convert export-web`: the folder it writes (index.html naming the model, every player file, the
model's bytes unchanged), and its errors (exit code 2, a message naming the file, nothing written)."""
from __future__ import annotations

from pathlib import Path

from stg_runtime.web.export import PLAYER_FILES, player_file
from stg_train.cli.convert import main

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "formats" / "vectors" / "sh.stg"


def test_export_writes_a_self_contained_folder(tmp_path, capsys):
    out = tmp_path / "site"
    assert main(["export-web", str(MODEL), str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted([*PLAYER_FILES, "sh.stg"])
    assert (out / "sh.stg").read_bytes() == MODEL.read_bytes()
    html = (out / "index.html").read_text()
    assert '<meta name="stg-model" content="sh.stg">' in html
    assert "http://" not in html and "https://" not in html  # nothing from elsewhere
    for name in PLAYER_FILES:
        if name.endswith(".js"):
            text = (out / name).read_bytes()
            assert text == player_file(name) and b"http://" not in text and b"https://" not in text
    assert "python -m http.server" in capsys.readouterr().out
    assert main(["export-web", str(out / "sh.stg"), str(out)]) == 0  # again, in place
    assert (out / "sh.stg").read_bytes() == MODEL.read_bytes()


def test_export_refuses_bad_input_and_writes_nothing(tmp_path, capsys):
    bad = ROOT / "tests" / "runtime" / "malicious" / "degree_1e9.stg"
    out = tmp_path / "site"
    assert main(["export-web", str(bad), str(out)]) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert err.startswith("stg-convert: error: ") and "degree_1e9.stg" in err and "degrees" in err
    assert main(["export-web", str(tmp_path / "none.stg"), str(out)]) == 2
    assert "none.stg" in capsys.readouterr().err and not out.exists()
    (tmp_path / "file").write_text("x")
    assert main(["export-web", str(MODEL), str(tmp_path / "file")]) == 2
    assert "not a folder" in capsys.readouterr().err
