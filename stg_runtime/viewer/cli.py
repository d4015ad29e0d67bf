"""`stg-view`: look around a `.stg` model in the browser (viser), as it plays."""
from __future__ import annotations

import argparse
import importlib.util
import sys

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


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is a number 0..65535, got {text!r}")
    return port


def _pixels(text: str) -> int:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w > 0 and h > 0:
            return w * h
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"size must look like 1280x720, got {text!r}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split(":", 1)[1].strip(), epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="the .stg model to show")
    p.add_argument("--port", type=_port, default=8080, help="port to serve on (default %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default %(default)s: this machine only)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                   help="where the Player renders (default auto: the GPU when numba sees one)")
    p.add_argument("--max-size", type=_pixels, default=1280 * 720, metavar="WxH",
                   help="largest picture sent, in pixels as WxH (the browser's canvas is scaled down to "
                        "it, keeping its shape; default 1280x720)")
    p.add_argument("--preview-size", type=_pixels, default=320 * 180, metavar="WxH",
                   help="picture size while the camera moves (default 320x180)")
    p.add_argument("--jpeg-quality", type=int, default=90, metavar="Q", help="JPEG quality 1..100 (default 90)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if importlib.util.find_spec("viser") is None:
        print(f"{PROG}: error: the viewer needs viser: python -m pip install 'spacetime-gaussians[viewer]' "
              "(or -e \".[viewer]\" in a checkout)", file=sys.stderr)
        return 2
    from ..format import FormatError
    from .frames import ViewSettings
    from .server import PortInUse, serve

    settings = ViewSettings(max_pixels=args.max_size, preview_pixels=args.preview_size,
                            jpeg_quality=min(max(args.jpeg_quality, 1), 100))

    def ready(viewer) -> None:
        print(f"{PROG}: serving {args.model} ({viewer.player.kind}, {viewer.player.device}) at {viewer.url} "
              "(Ctrl-C stops)", file=sys.stderr, flush=True)

    try:
        serve(args.model, host=args.host, port=args.port, device=args.device, settings=settings, ready=ready)
    except (FormatError, PortInUse, RuntimeError, ValueError, OSError) as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    print(f"{PROG}: stopped", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
