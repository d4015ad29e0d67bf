"""The command-line matrix: for every command, its options alone, every pair of them, and bad values.

A command is described by a `Command`: the arguments every case starts from (`base`), one valid
fragment per option (`options`), the pairs that must be refused (`refused_pairs`, with what the error
line names), the bad values (`bad`: fragment -> what the error line must name) and what a success
promises (`outputs`: paths that must exist). `cases()` expands them into `Case`s:

    every option alone                       -> success
    every pair of options                    -> success, or exit 2 where listed in refused_pairs
    every bad value                          -> exit 2, one line `PROG: error: ...` naming it

Strings hold placeholders filled from the `inputs` fixture ({data}, {model}, {path}, ...) and {out}, a
fresh path in an empty folder of its own (tests/cli/test_matrix.py checks that a refused case leaves
that folder empty: nothing half-written).

stg-train and stg-view are checked without training or serving (`validate`): the library calls
they end in (stg_train.pipeline.train / run_demo, stg_train.distributed.run.train_parallel,
stg_runtime.viewer.server.serve) are replaced by stand-ins with the real signatures, so every option
is parsed, checked and passed on for real; tests/cli/test_runs.py trains a few steps where a
combination must really run.

To add a command: write its Command below and add it to COMMANDS; to add an option, add its valid
fragment to `options` and its bad values to `bad` (and any pair it cannot join to `refused_pairs`).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Case:
    prog: str            # the command: stg-train, stg-convert, ...
    argv: tuple          # its arguments, with placeholders
    expect: str          # "ok" or "error"
    names: str = ""      # for "error": a regex the error line must match (the option or file, the problem)
    outputs: tuple = ()  # for "ok": paths (with placeholders) that must exist afterwards
    validate: bool = False  # the library call is a stand-in (see the module doc)

    @property
    def id(self) -> str:
        return f"{self.prog} {' '.join(self.argv)}".replace("{", "").replace("}", "")


@dataclass
class Command:
    prog: str
    base: tuple
    options: dict                      # name -> argv fragment (tuple) that is valid alone
    outputs: tuple = ()
    refused_pairs: dict = field(default_factory=dict)  # frozenset({name, name}) -> regex of the error
    bad: dict = field(default_factory=dict)            # argv fragment (tuple) -> regex of the error
    validate: bool = False
    pairs: bool = True
    base_ok: bool = True  # whether `base` alone succeeds (it is a case of its own then)

    def cases(self) -> list[Case]:
        out = [Case(self.prog, self.base, "ok", outputs=self.outputs, validate=self.validate)] if self.base_ok else []
        for name, frag in self.options.items():
            out.append(Case(self.prog, self.base + frag, "ok", outputs=self.outputs, validate=self.validate))
        if self.pairs:
            for (a, fa), (b, fb) in itertools.combinations(self.options.items(), 2):
                refused = self.refused_pairs.get(frozenset((a, b)))
                out.append(Case(self.prog, self.base + fa + fb, "error" if refused else "ok", names=refused or "",
                                outputs=() if refused else self.outputs, validate=self.validate))
        for frag, names in self.bad.items():
            out.append(Case(self.prog, self.base + frag if frag[:1] != ("!",) else frag[1:], "error", names=names,
                            validate=self.validate))
        return out


def _bad_numbers(option: str, values=("0", "-1", "abc", "1.5")) -> dict:
    """option VALUE -> the option named in the error, for values a positive integer option refuses."""
    return {(option, v): option for v in values}


# -- stg-train --------------------------------------------------------------------------------------
TRAIN = Command(
    "stg-train", ("{data}", "--out", "{out}", "--quiet"),
    options={
        "model": ("--model", "lite"), "iterations": ("--iterations", "3"), "splatter": ("--splatter", "torch"),
        "device": ("--device", "cpu"), "resume": ("--resume",), "force": ("--force",),
        "segment-frames": ("--segment-frames", "2"), "segments": ("--segments", "0"),
        "segment-context": ("--segment-context", "0"), "ray": ("--ray",), "checkpoint-every": ("--checkpoint-every", "1"), "batch": ("--batch", "1"),
        "points": ("--points", "50"), "init": ("--init", "volume"), "init-every": ("--init-every", "2"),
        "motion-init": ("--motion-init", "zero"), "seed": ("--seed", "1"), "layout": ("--layout", "n3v"),
        "fps": ("--fps", "25"), "test-camera": ("--test-camera", "cam01"), "downscale": ("--downscale", "2"),
        "frames": ("--frames", "3"), "from-video": ("--from-video",), "near-far": ("--near", "1", "--far", "20"),
        "threads": ("--threads", "1"), "no-check": ("--no-check",), "no-guided": ("--no-guided",),
        "viewer": ("--viewer", "{port}"), "appearance": ("--appearance",), "pose-refine": ("--pose-refine",),
        "lens-falloff": ("--lens-falloff", "-0.3"), "edge-weight": ("--edge-weight", "1"),
        "segment-schedule": ("--segment-schedule", "warm"),
    },
    refused_pairs={frozenset(("resume", "force")): "--resume.*--force",
                   frozenset(("ray", "viewer")): "--viewer.*--ray"},
    bad={**_bad_numbers("--iterations"), **_bad_numbers("--batch"), **_bad_numbers("--points"),
         **_bad_numbers("--checkpoint-every"), **_bad_numbers("--segment-frames"), **_bad_numbers("--init-every"),
         **_bad_numbers("--threads"), **_bad_numbers("--downscale"), **_bad_numbers("--frames"),
         ("--threads", "100000"): "--threads", ("--downscale", "1000"): "downscale|1000",
         ("--frames", "1000"): "1000", ("--seed", "-1"): "--seed", ("--seed", "abc"): "--seed",
         ("--fps", "0"): "--fps", ("--fps", "-1"): "--fps", ("--fps", "nan"): "--fps", ("--fps", "abc"): "--fps",
         ("--model", "medium"): "--model", ("--splatter", "cuda"): "--splatter", ("--device", "gpu"): "--device",
         ("--init", "x"): "--init", ("--motion-init", "x"): "--motion-init", ("--layout", "x"): "--layout",
         ("--layout", "technicolor"): "undist|technicolor", ("--test-camera", "cam99"): "cam99",
         ("--segments", "5"): "--segments 5", ("--segments", "x"): "--segments", ("--segments", "-1"): "--segments",
         ("--segment-context", "-1"): "--segment-context", ("--segment-context", "x"): "--segment-context",
         ("--segment-schedule", "x"): "--segment-schedule", ("--edge-weight", "0.5"): "--edge-weight", ("--edge-weight", "11"): "--edge-weight",
         ("--edge-weight", "nan"): "--edge-weight", ("--edge-weight", "x"): "--edge-weight",
         ("--lens-falloff", "x"): "--lens-falloff", ("--lens-falloff", "-1"): "--lens-falloff",
         ("--lens-falloff=0,0,1",): "--lens-falloff", ("--lens-falloff", "nan"): "--lens-falloff",
         ("--viewer", "70000"): "--viewer", ("--viewer", "x"): "--viewer", ("--near", "1"): "--near.*--far",
         ("--near", "5", "--far", "1"): "--far", ("--near", "-1", "--far", "1"): "--near",
         ("--gpus", "0"): "--gpus.*--device cuda", ("--ray", "--gpus", "0"): "--gpus|--ray",
         ("--unknown",): "--unknown", ("--demo",): "DATA.*--demo|--demo.*DATA",
         ("!", "{missing}", "--out", "{out}"): "missing", ("!", "{text}", "--out", "{out}"): "text.txt",
         ("!", "{folder}", "--out", "{out}"): "folder", ("!", "{one_cam}", "--out", "{out}"): "one_cam|camera",
         ("!", "{data}", "--out", "{text}"): "--out.*text.txt", ("!", "{data}", "--out", "{text}/run"): "text.txt",
         ("!", "{data}"): "--out", ("!",): "DATA"},
    validate=True)

TRAIN_DEMO = Command(
    "stg-train", ("--demo", "--out", "{out}", "--quiet"),
    options={"iterations": ("--iterations", "3"), "model": ("--model", "lite"), "points": ("--points", "50"),
             "viewer": ("--viewer", "{port}")},
    bad={("--ray",): "--ray", ("--gpus", "0", "--device", "cuda"): "--gpus|--ray|--demo"},
    validate=True)

# -- stg-eval ---------------------------------------------------------------------------------------
EVAL = Command(
    "stg-eval", ("{model}", "{data}", "--no-lpips", "--quiet"),
    options={"json": ("--json", "{out}"), "layout": ("--layout", "n3v"), "fps": ("--fps", "30"),
             "test-camera": ("--test-camera", "cam01"), "downscale": ("--downscale", "2"),
             "frames": ("--frames", "3"), "from-video": ("--from-video",),
             "dynamic-threshold": ("--dynamic-threshold", "0.2"), "any-cameras": ("--any-cameras",),
             "align-poses": ("--align-poses",)},
    bad={("--json", "{folder}"): "--json.*folder", ("--json", "{missing}/x.json"): "--json",
         ("--fps", "25"): "fps", ("--test-camera", "cam99"): "cam99", ("--downscale", "0"): "--downscale",
         ("--dynamic-threshold", "-1"): "--dynamic-threshold", ("--dynamic-threshold", "abc"): "--dynamic-threshold",
         ("--frames", "0"): "--frames", ("--layout", "x"): "--layout",
         ("!", "{missing}", "{data}"): "missing", ("!", "{empty}", "{data}"): "empty",
         ("!", "{folder}", "{data}"): "folder", ("!", "{text}", "{data}"): "text.txt",
         ("!", "{model}", "{missing}"): "missing", ("!", "{model}", "{text}"): "text.txt",
         ("!", "{model}", "{other}", "--no-lpips", "--quiet"): "camera", ("!", "{model}"): "DATA|data"},
    outputs=())

# -- stg-render -------------------------------------------------------------------------------------
RENDER = Command(
    "stg-render", ("{model}", "--out", "{out}.mp4", "--quiet"),
    options={"camera": ("--camera", "1"), "orbit": ("--orbit",), "path": ("--path", "{path}"),
             "size": ("--size", "40x30"), "start": ("--start", "0.05"), "end": ("--end", "0.08"),
             "fps": ("--fps", "40"), "device": ("--device", "cpu")},
    outputs=("{out}.mp4",),
    refused_pairs={frozenset(("camera", "orbit")): "--camera|--orbit", frozenset(("camera", "path")): "--camera|--path",
                   frozenset(("orbit", "path")): "--orbit|--path",
                   # a 4-camera path from 0.05 s, or up to 0.08 s, needs more frames than those times have
                   frozenset(("path", "start")): "--path", frozenset(("path", "end")): "--path"},
    bad={("--camera", "9"): "--camera 9", ("--camera", "-1"): "--camera", ("--camera", "x"): "--camera",
         ("--size", "0x0"): "--size", ("--size", "100000x100000"): "--size", ("--size", "abc"): "--size",
         ("--start", "-5"): "--start", ("--start", "99"): "--start", ("--end", "99"): "--end",
         ("--start", "0.1", "--end", "0.05"): "--end", ("--start", "nan"): "--start", ("--fps", "0"): "--fps",
         ("--fps", "-1"): "--fps", ("--device", "gpu"): "--device",
         ("--path", "{path_long}"): "--path.*8 cameras", ("--path", "{missing}"): "missing",
         ("--path", "{empty}"): "empty", ("--path", "{folder}"): "folder", ("--path", "{text}"): "text.txt",
         ("--path", "{model}"): "model.stg",
         ("!", "{model}", "--out", "{out}.xyz"): "--out.*xyz", ("!", "{model}", "--out", "{text}"): "--out.*text.txt",
         ("!", "{model}", "--out", "{text}/v.mp4"): "--out.*text.txt",
         ("!", "{model}", "--out", "{folder}", "--size", "33x25", "--demo"): "--demo",
         ("!", "{missing}", "--out", "{out}.mp4"): "missing", ("!", "{empty}", "--out", "{out}.mp4"): "empty",
         ("!", "{folder}", "--out", "{out}.mp4"): "folder", ("!", "{text}", "--out", "{out}.mp4"): "text.txt",
         ("!", "--out", "{out}.mp4"): "MODEL", ("!", "{model}"): "--out"})

#: bad_camera_paths' faults (tests/cli/conftest.py) -> what the error names: the camera and the field.
CAMERA_PATH_FAULTS = {"no_fx": '"fx" is missing', "fx_text": '"fx" must be a positive number',
                      "width_text": '"width" must be a whole number', "width_zero": '"width"',
                      "w2c_12": '"world_to_camera" must be 16 numbers', "w2c_scaled": '"world_to_camera".*rotation',
                      "w2c_text": '"world_to_camera"', "not_object": "expected a camera object", "fisheye_no_k": 'intrinsics: "k1" is missing'}
RENDER.bad.update({("--path", f"{{path_{name}}}"): f"--path .*: camera 1: {text}"
                   for name, text in CAMERA_PATH_FAULTS.items()})

RENDER_KINDS = Command(  # every kind of --out alone, with an odd --size (rounded for yuv420p, with a note)
    "stg-render", ("{model}", "--quiet", "--size", "33x25", "--end", "0.04"),
    options={"folder": ("--out", "{out}"), "folder-slash": ("--out", "{out}.d/"), "mp4": ("--out", "{out}.mp4"),
             "mov": ("--out", "{out}.mov"), "mkv": ("--out", "{out}.mkv"), "webm": ("--out", "{out}.webm"),
             "gif": ("--out", "{out}.gif"), "path-one": ("--path", "{path_one}", "--out", "{out}.mp4")},
    pairs=False, base_ok=False)

# -- stg-synth --------------------------------------------------------------------------------------
SYNTH = Command(
    "stg-synth", ("{out}", "--quiet", "--cameras", "2", "--frames", "2", "--size", "16x12"),
    options={"fps": ("--fps", "10"), "focal": ("--focal", "20"), "fisheye": ("--fisheye", "180"),
             "pinhole-dome": ("--pinhole-dome", "90"), "seed": ("--seed", "3"), "supersample": ("--supersample", "2"),
             "no-png": ("--no-png",), "realistic": ("--realistic",), "gain": ("--gain", "0.5"),
             "white-balance": ("--white-balance", "0.1"), "vignetting": ("--vignetting", "0"),
             "noise": ("--noise", "0.02"), "pose-rotation": ("--pose-rotation", "0.5"),
             "pose-translation": ("--pose-translation", "0.02")},
    outputs=("{out}/scene.json",),
    refused_pairs={frozenset(("fisheye", "pinhole-dome")): "--fisheye|--pinhole-dome",
                   frozenset(("focal", "fisheye")): "--focal", frozenset(("focal", "pinhole-dome")): "--focal",
                   # the realistic capture is of the N3V rig, not of the domes
                   **{frozenset((knob, dome)): "--realistic.*dome|--fisheye|--pinhole-dome"
                      for knob in ("realistic", "gain", "white-balance", "vignetting", "noise", "pose-rotation",
                                   "pose-translation") for dome in ("fisheye", "pinhole-dome")}},
    bad={**_bad_numbers("--cameras"), **_bad_numbers("--frames"), **_bad_numbers("--supersample"),
         ("--size", "4x4"): "--size", ("--size", "100000x100"): "--size", ("--size", "x"): "--size",
         ("--fps", "0"): "--fps", ("--fps", "nan"): "--fps", ("--focal", "-1"): "--focal",
         ("--fisheye", "0"): "--fisheye", ("--fisheye", "400"): "--fisheye", ("--pinhole-dome", "180"): "--pinhole-dome",
         ("--seed", "x"): "--seed", ("--gain", "-1"): "--gain", ("--noise", "x"): "--noise",
         ("--vignetting", "inf"): "--vignetting", ("--pose-rotation", "-0.1"): "--pose-rotation",
         ("--white-balance", "nan"): "--white-balance", ("--pose-translation", "x"): "--pose-translation",
         ("!", "{text}"): "text.txt", ("!", "{text}/sub"): "text.txt", ("!",): "out_dir"})

# -- stg-view (validate: serve() is a stand-in) -----------------------------------------------------
VIEW = Command(
    "stg-view", ("{model}",),
    options={"port": ("--port", "{port}"), "host": ("--host", "127.0.0.1"), "device": ("--device", "cpu"),
             "max-size": ("--max-size", "640x480"), "preview-size": ("--preview-size", "160x120"),
             "jpeg-quality": ("--jpeg-quality", "50")},
    bad={("--port", "70000"): "--port", ("--port", "x"): "--port", ("--device", "gpu"): "--device",
         ("--max-size", "0x0"): "--max-size", ("--max-size", "abc"): "--max-size",
         ("--preview-size", "1920x1080"): "--preview-size", ("--jpeg-quality", "0"): "--jpeg-quality",
         ("--jpeg-quality", "101"): "--jpeg-quality", ("!", "{missing}"): "missing", ("!", "{folder}"): "folder",
         ("!",): "model"},
    validate=True)

# -- stg-convert ------------------------------------------------------------------------------------
COMPRESS = Command(
    "stg-convert", ("compress", "{model}", "{out}.stg"),
    options={"preset": ("--preset", "small"), "encoding": ("--encoding", "position=f16"),
             "prune-opacity": ("--prune-opacity", "0.01"), "prune-unseen": ("--no-prune-unseen",),
             "order": ("--order", "none"), "level": ("--level", "1"), "data": ("--data", "{data}"),
             "downscale": ("--downscale", "1")},
    outputs=("{out}.stg",),
    bad={("--preset", "tiny"): "--preset", ("--encoding", "position=u4"): "--encoding|u4",
         ("--encoding", "size=u8"): "--encoding|size", ("--prune-opacity", "2"): "--prune-opacity",
         ("--prune-opacity", "x"): "--prune-opacity", ("--level", "10"): "--level", ("--level", "x"): "--level",
         ("--data", "{missing}"): "missing", ("--data", "{text}"): "text.txt", ("--downscale", "0"): "--downscale",
         ("--finetune", "2"): "--data", ("--prune-fraction", "1"): "--prune-fraction",
         ("--finetune", "0"): "--finetune", ("--finetune-quantised", "2"): "--finetune-quantised.*--finetune",
         ("--finetune-quantised", "0"): "--finetune-quantised", ("--prune-stages", "0"): "--prune-stages",
         ("--prune-stages", "2"): "--prune-stages.*--finetune",
         ("--still", "0.2"): "--still.*--finetune", ("--still", "2"): "--still", ("--still", "x"): "--still",
         ("!", "compress", "{model}", "{model}"): "model.stg.*input",
         ("!", "compress", "{model}", "{folder}"): "folder", ("!", "compress", "{model}", "{missing}/x.stg"): "missing",
         ("!", "compress", "{missing}", "{out}.stg"): "missing", ("!", "compress", "{empty}", "{out}.stg"): "empty",
         ("!", "compress", "{text}", "{out}.stg"): "text.txt", ("!", "compress", "{folder}", "{out}.stg"): "folder",
         ("!", "compress", "{model}"): "OUT"})

EXPORT_PLY = Command(
    "stg-convert", ("export-ply", "{model}", "{out}.ply", "--time", "0.05"),
    options={}, outputs=("{out}.ply",),
    bad={("!", "export-ply", "{model}", "{out}.ply"): "--time", ("!", "export-ply", "{model}", "{out}.ply", "--time", "9"): "--time",
         ("!", "export-ply", "{model}", "{out}.ply", "--time", "x"): "--time",
         ("!", "export-ply", "{model}", "{model}", "--time", "0"): "input",
         ("!", "export-ply", "{missing}", "{out}.ply", "--time", "0"): "missing",
         ("!", "export-ply", "{text}", "{out}.ply", "--time", "0"): "text.txt"})

IMPORT_3DGS = Command(
    "stg-convert", ("import-3dgs", "{ply}", "{out}.stg"),
    options={"fps": ("--fps", "25"), "frames": ("--frames", "3")},
    outputs=("{out}.stg",),
    bad={("--fps", "0"): "--fps", ("--frames", "0"): "--frames", ("--frames", "x"): "--frames",
         ("--cameras", "{missing}"): "missing", ("--cameras", "{text}"): "text.txt",
         ("!", "import-3dgs", "{ply}", "{ply}"): "input", ("!", "import-3dgs", "{missing}", "{out}.stg"): "missing",
         ("!", "import-3dgs", "{empty}", "{out}.stg"): "empty", ("!", "import-3dgs", "{model}", "{out}.stg"): "model.stg"})

MERGE = Command(
    "stg-convert", ("merge", "{model}", "{out}.stg"),
    options={"crossfade": ("--crossfade", "2")}, outputs=("{out}.stg",),
    bad={("--crossfade", "-1"): "--crossfade", ("--crossfade", "x"): "--crossfade",
         ("!", "merge", "{model}", "{model}"): "input", ("!", "merge", "{model}", "{model}", "{out}.stg"): "model.stg",
         ("!", "merge", "{missing}", "{out}.stg"): "missing", ("!", "merge", "{text}", "{out}.stg"): "text.txt",
         ("!", "merge", "{model}"): "OUT|output|arguments"})

IMPORT_REFERENCE = Command(
    "stg-convert", ("import-reference", "{ply}", "{out}.stg"), options={}, pairs=False, base_ok=False,
    bad={("!", "import-reference", "{ply}", "{ply}"): "input", ("--fps", "0"): "--fps",
         ("--start-frame", "-1"): "--start-frame", ("--segment-frames", "0"): "--segment-frames",
         ("--duration", "x"): "--duration", ("--activation", "x"): "--activation",
         ("--decoder", "{missing}"): "missing|--decoder",
         ("!", "import-reference", "{missing}", "{out}.stg"): "missing"})

COMMANDS = [TRAIN, TRAIN_DEMO, EVAL, RENDER, RENDER_KINDS, SYNTH, VIEW, COMPRESS, EXPORT_PLY, IMPORT_3DGS, MERGE,
            IMPORT_REFERENCE]


def export_web() -> Command | None:
    """stg-convert export-web, where this checkout has it."""
    try:
        from stg_runtime.web import export  # noqa: F401
    except ImportError:
        return None
    return Command("stg-convert", ("export-web", "{model}", "{out}"), options={}, outputs=("{out}/index.html",),
                   bad={("!", "export-web", "{model}", "{text}"): "text.txt",
                        ("!", "export-web", "{missing}", "{out}"): "missing",
                        ("!", "export-web", "{text}", "{out}"): "text.txt"})


def all_cases() -> list[Case]:
    commands = COMMANDS + [c for c in [export_web()] if c is not None]
    return [case for command in commands for case in command.cases()]
