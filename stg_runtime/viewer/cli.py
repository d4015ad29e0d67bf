"""`stg-view`: look around a `.stg` model in the browser (viser), as it plays."""
from __future__ import annotations

import argparse
import importlib.util
import os
import sys

from ..arguments import Parser, error, port

PROG = "stg-view"

EPILOG = """examples:
  stg-view run/model.stg                         open http://127.0.0.1:8080 in a browser
  stg-view run/model.stg --port 8081 --device cuda
  stg-view run/model.stg --host 0.0.0.0          reachable from other machines (no authentication!)
On a remote GPU server, keep the default host and tunnel the port: ssh -L 8080:127.0.0.1:8080 server

In the browser: drag to orbit, right-drag to pan, scroll to zoom; the panel has the time (slider, play,
pause, loop, speed), the render mode (rgb, depth, alpha, base colour for full models), jumps to the
training cameras, a PNG screenshot and camera-path JSON files for `stg-render --path`.
Needs the viewer extra: python -m pip install -e ".[viewer]".
Exit codes: 0 stopped (Ctrl-C), 2 bad model, port in use, no GPU for --device cuda, viser missing."""


def _pixels(text: str) -> int:
    from ..arguments import image_size

    w, h = image_size(text, minimum=8)
    return w * h


def _quality(text: str) -> int:
    if not text.isdigit() or not 1 <= int(text) <= 100:
        raise argparse.ArgumentTypeError(f"JPEG quality is a whole number 1..100, got {text!r}")
    return int(text)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog=PROG, description=__doc__.split(":", 1)[1].strip(), epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the .stg model to show")
    p.add_argument("--port", type=port, default=8080, help="port to serve on (default %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default %(default)s: this machine only)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                   help="where the Player renders (default auto: the GPU when numba sees one)")
    p.add_argument("--max-size", type=_pixels, default=1280 * 720, metavar="WxH",
                   help="largest picture sent, in pixels as WxH (the browser's canvas is scaled down to "
                        "it, keeping its shape; default 1280x720)")
    p.add_argument("--preview-size", type=_pixels, default=320 * 180, metavar="WxH",
                   help="picture size while the camera moves (default 320x180)")
    p.add_argument("--jpeg-quality", type=_quality, default=90, metavar="Q", help="JPEG quality 1..100 (default 90)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.preview_size > args.max_size:
        return error(PROG, "--preview-size: must not be larger than --max-size")
    if not os.path.isfile(args.model):
        what = "is a folder, not a .stg model" if os.path.isdir(args.model) else "no such file"
        return error(PROG, f"{args.model}: {what}")
    if importlib.util.find_spec("viser") is None:
        return error(PROG, "the viewer needs viser: python -m pip install 'spacetime-gaussians[viewer]' "
                           "(or -e \".[viewer]\" in a checkout)")
    if args.device == "cuda":
        from ..cuda.device import usable

        if not usable():
            return error(PROG, "--device cuda: numba sees no CUDA GPU here: use --device cpu (or auto)")
    from ..format import FormatError
    from .frames import ViewSettings
    from .server import PortInUse, serve

    settings = ViewSettings(max_pixels=args.max_size, preview_pixels=args.preview_size,
                            jpeg_quality=args.jpeg_quality)

    def ready(viewer) -> None:
        print(f"{PROG}: serving {args.model} ({viewer.player.kind}, {viewer.player.device}) at {viewer.url} "
              "(Ctrl-C stops)", file=sys.stderr, flush=True)

    try:
        serve(args.model, host=args.host, port=args.port, device=args.device, settings=settings, ready=ready)
    except PortInUse as e:
        return error(PROG, f"--port {args.port}: {e}: choose another with --port N")
    except FormatError as e:
        return error(PROG, str(e))
    except (RuntimeError, ValueError) as e:
        return error(PROG, f"--device {args.device}: {e}" if args.device == "cuda" else str(e))
    except OSError as e:
        return error(PROG, f"--host {args.host}: {e.strerror or e}")
    except KeyboardInterrupt:
        pass
    print(f"{PROG}: stopped", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
