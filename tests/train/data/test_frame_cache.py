"""The frame cache (stg_train.data.frames.build_frame_cache) when two processes need it at once."""
import subprocess
import sys
import textwrap

import numpy as np

BUILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from stg_train.data.frames import build_frame_cache

    cache_dir, log = sys.argv[1], sys.argv[2]

    def fill(arr):
        with open(log, "a") as f:
            f.write("fill\\n")
        time.sleep(1.5)  # long enough for the other process to arrive while this one builds
        arr[:] = np.arange(arr.size, dtype=np.uint64).reshape(arr.shape) % 251

    frames = build_frame_cache(cache_dir, {"source": "test"}, (2, 3, 4, 5, 3), fill)
    print(int(frames.astype(np.int64).sum()))
""")


def test_two_processes_share_one_build(tmp_path):
    cache_dir, log = tmp_path / "cache", tmp_path / "fills.log"
    runs = [subprocess.Popen([sys.executable, "-c", BUILD, str(cache_dir), str(log)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [run.communicate(timeout=120) for run in runs]
    for run, (out, err) in zip(runs, results):
        assert run.returncode == 0, err
    expected = int((np.arange(2 * 3 * 4 * 5 * 3) % 251).sum())
    assert [int(out) for out, _ in results] == [expected, expected]
    assert log.read_text().count("fill") == 1  # the second process waited and read the first one's cache
    assert sorted(p.name for p in cache_dir.iterdir()) == ["frames_uint8.json", "frames_uint8.lock", "frames_uint8.npy"]
