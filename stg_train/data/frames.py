"""Frames on disk -> the frame cache: frame sources (image files or a video per camera), readers,
probing, and build_dataset, which every layout reader ends with.

Frames are decoded once into a cache file, `frames_uint8.npy`, a uint8 numpy array of shape
(cameras, frames, H, W, 3) (RGB) under <dataset>/.stg_cache/, rebuilt only when the source files or
options change, and read lazily from it as a memory map.

With `lazy=True` nothing is decoded when the dataset is loaded: its frames are a ChunkedFrames, cut
into chunks of frames (the whole video, or the segments of a long video: Dataset.chunked), each decoded
into its own cache file on its first read. A segment's training run then reads and decodes only its own
frames, and runs of different segments (on several GPUs or machines) never write the same file.
"""
from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from stg_runtime.atomic import atomic_output, remove_leftovers, write_atomic
from stg_runtime.camera import Camera

from .dataset import DataError, Dataset

CACHE_NAME = "frames_uint8.npy"
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
#: Frames per second of layouts that store none.
DEFAULT_FPS = 30.0


# -- reading one camera's frames -------------------------------------------------------------------
@dataclass
class FrameSource:
    """The frames of one camera: a sorted list of image files, or one video file."""

    images: list[Path] | None = None
    video: Path | None = None

    @property
    def path(self) -> Path:
        return self.video if self.video is not None else self.images[0].parent

    @property
    def files(self) -> list[Path]:
        return [self.video] if self.video is not None else list(self.images)


def image_files(folder: Path) -> list[Path]:
    """Image files (png, jpg) directly in `folder`, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file (png, jpg), or DataError naming the file."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        _check_readable(path)
        raise DataError(f"{path}: cannot be read as an image")
    return img[..., ::-1]


def _check_readable(path: Path) -> None:
    """DataError saying why when `path` cannot be opened at all (OpenCV only says that it failed)."""
    try:
        with open(path, "rb"):
            pass
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({e.strerror or e})") from None


def probe_video(path: Path) -> tuple[int, int, int, float]:
    """(frame count, width, height, fps) of a video, or DataError."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            _check_readable(path)
            raise DataError(f"{path}: cannot be opened as a video")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        if count <= 0:  # no frame count in the container: count by decoding
            count = 0
            while cap.grab():
                count += 1
        if count <= 0 or width <= 0 or height <= 0:
            raise DataError(f"{path}: the video has zero frames")
        return count, width, height, fps
    finally:
        cap.release()


def video_frames(path: Path, num_frames: int, start: int = 0):
    """Frames start .. start + num_frames - 1 of a video as (H, W, 3) uint8 RGB; DataError if it has
    fewer. The frames before `start` are grabbed in order (not seeked), so frame k is the same frame
    whichever range it is decoded in."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DataError(f"{path}: cannot be opened as a video")
    try:
        for k in range(start):
            if not cap.grab():
                raise DataError(f"{path}: decoded only {k} of {start + num_frames} frames")
        for k in range(num_frames):
            ok, bgr = cap.read()
            if not ok or bgr is None:
                raise DataError(f"{path}: decoded only {start + k} of {start + num_frames} frames")
            yield np.ascontiguousarray(bgr[..., ::-1])
    finally:
        cap.release()


def probe(source: FrameSource) -> tuple[int, int, int, float | None]:
    """(frame count, width, height, fps or None) of one camera's frames."""
    if source.video is not None:
        count, w, h, fps = probe_video(source.video)
        return count, w, h, (fps if fps > 0 else None)
    h, w = read_image(source.images[0]).shape[:2]
    return len(source.images), w, h, None


def resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """rgb (H, W, 3) resized to width x height by area averaging (OpenCV's INTER_AREA)."""
    import cv2

    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _decode(source: FrameSource, num_frames: int, start: int = 0):
    """(label, frame) pairs of frames start .. start + num_frames - 1."""
    if source.video is not None:
        for k, rgb in enumerate(video_frames(source.video, num_frames, start)):
            yield f"{source.video} frame {start + k}", rgb
    else:
        for f in source.images[start:start + num_frames]:
            yield str(f), read_image(f)


@dataclass
class FrameDecoder:
    """Decodes frame ranges of every camera's source into an array: the frame cache's filler.

    sources: one FrameSource per camera; size: the sources' (width, height); out_size: the cached
    (width, height) (size // downscale, INTER_AREA)."""

    sources: list
    size: tuple
    out_size: tuple

    def fill(self, arr: np.ndarray, start: int = 0, progress=None) -> None:
        """Write frames start .. start + F - 1 of every camera into arr (C, F, H', W', 3) uint8.
        progress(done, total): called per decoded frame. Raises DataError naming a frame of another size."""
        (width, height), (out_w, out_h) = self.size, self.out_size
        total, done = arr.shape[0] * arr.shape[1], 0
        for ci, src in enumerate(self.sources):
            for k, (label, rgb) in enumerate(_decode(src, arr.shape[1], start)):
                if rgb.shape[:2] != (height, width):
                    raise DataError(f"{label}: is {rgb.shape[1]}x{rgb.shape[0]}, expected {width}x{height}")
                arr[ci, k] = resize(rgb, out_w, out_h) if (out_w, out_h) != (width, height) else rgb
                done += 1
                if progress is not None:
                    progress(done, total)


# -- the frame cache -------------------------------------------------------------------------------
def build_frame_cache(cache_dir, signature: dict, shape: tuple, fill: Callable[[np.ndarray], None]) -> np.memmap:
    """Open the frame cache in cache_dir, (re)building it when it is missing or was made from other data.

    signature: JSON-able description of the source (files, sizes, modification times, options); the
    cache is reused only when it matches. shape: (C, F, H, W, 3). fill(array): writes every frame into
    the writable memmap it is given. The file is written under a temporary name and renamed when
    complete, so an interrupted build is never taken for a cache. Processes that need the same cache
    at once (two runs on one dataset) take turns on a lock file in cache_dir: one builds it, the others
    then find it built. Returns a read-only memmap.
    """
    cache_dir = Path(cache_dir)
    path, meta_path = cache_dir / CACHE_NAME, cache_dir / "frames_uint8.json"
    wanted = dict(signature, shape=list(shape))
    cached = _open_cache(path, meta_path, wanted)
    if cached is not None:
        return cached
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DataError(f"{cache_dir}: cannot create the frame cache folder ({e})") from None
    with _cache_lock(cache_dir):
        cached = _open_cache(path, meta_path, wanted)  # built by another process while this one waited
        if cached is not None:
            return cached
        remove_leftovers(cache_dir, CACHE_NAME)  # of an interrupted build
        with atomic_output(path) as tmp:
            try:
                arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=tuple(shape))
            except OSError as e:
                raise DataError(f"{tmp}: cannot write the frame cache ({e})") from None
            fill(arr)
            arr.flush()
            del arr
        write_atomic(meta_path, json.dumps(wanted, indent=1))
    return np.load(path, mmap_mode="r")


def _open_cache(path: Path, meta_path: Path, wanted: dict) -> np.memmap | None:
    """The cache at `path`, read-only, when it is complete and its metadata equal `wanted`; else None."""
    if not (path.exists() and meta_path.exists()):
        return None
    try:
        if json.loads(meta_path.read_text()) == wanted:
            arr = np.load(path, mmap_mode="r")
            if arr.shape == tuple(wanted["shape"]) and arr.dtype == np.uint8:
                return arr
    except (OSError, ValueError):
        pass
    return None


@contextmanager
def _cache_lock(cache_dir: Path) -> Iterator[None]:
    """Hold an exclusive lock (fcntl.flock on cache_dir/frames_uint8.lock) for the block: a second
    process waits until the first has finished. Without fcntl (Windows) or where the file system
    refuses locks, no lock."""
    try:
        import fcntl
        handle = open(cache_dir / "frames_uint8.lock", "a")
    except (ImportError, OSError):
        yield
        return
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX)
        except OSError:
            pass
        yield  # the lock goes with the file's closing


class ChunkedFrames:
    """Frames (C, F, H, W, 3) uint8 RGB, decoded on their first read into cache files, one per chunk.

    cache_dir: the video's frame-cache folder; the chunk of every frame keeps the whole video's cache
    (cache_dir/frames_uint8.npy, as an eager load), any other chunk [a, a + n) its own subfolder
    cache_dir/frames_<a>-<a+n-1>. key: the cache signature (build_dataset's); shape: the whole video's;
    decoder: fills a chunk (FrameDecoder); chunks: (start, count) pairs covering frames 0..F-1 in order
    (default: one, the whole video); start, count: the frames of the video this object shows (a view:
    `frames[:, a:b]` reads only the chunks it overlaps). show_progress: a bar on stderr while a chunk
    is decoded.

    Indexing: frames[c, f] and frames[c, f, ...rest] (integers c, f: an array read from f's chunk) and
    frames[:, a:b] (a view). Pickled without its open memory maps, so a view sent to another process
    opens (or decodes) only its own chunks there.
    """

    dtype = np.dtype(np.uint8)
    ndim = 5

    def __init__(self, cache_dir, key: dict, shape: tuple, decoder: FrameDecoder, chunks=None, start: int = 0,
                 count: int | None = None, show_progress: bool = False):
        self.cache_dir, self.key, self.full_shape, self.decoder = Path(cache_dir), key, tuple(shape), decoder
        total = self.full_shape[1]
        self.chunks = [(0, total)] if chunks is None else [(int(a), int(n)) for a, n in chunks]
        if [a for a, _ in self.chunks] != [sum(n for _, n in self.chunks[:i]) for i in range(len(self.chunks))] \
                or sum(n for _, n in self.chunks) != total or any(n <= 0 for _, n in self.chunks):
            raise ValueError(f"chunks {self.chunks} do not cut frames 0-{total - 1} into consecutive ranges")
        self.start, self.count = int(start), total - int(start) if count is None else int(count)
        self.show_progress = show_progress
        self._open: dict[int, np.ndarray] = {}

    @property
    def shape(self) -> tuple:
        c, _, h, w, ch = self.full_shape
        return (c, self.count, h, w, ch)

    def __len__(self) -> int:
        return self.full_shape[0]

    def with_options(self, chunks=None, show_progress: bool | None = None) -> "ChunkedFrames":
        """These frames cut into other chunks and/or with progress bars switched on or off."""
        return ChunkedFrames(self.cache_dir, self.key, self.full_shape, self.decoder,
                             self.chunks if chunks is None else chunks, self.start, self.count,
                             self.show_progress if show_progress is None else show_progress)

    def chunk_dir(self, start: int, count: int) -> Path:
        """The cache folder of chunk [start, start + count)."""
        if (start, count) == (0, self.full_shape[1]):
            return self.cache_dir
        return self.cache_dir / f"frames_{start}-{start + count - 1}"

    def chunk_of(self, frame: int) -> tuple[int, int]:
        """(start, count) of the chunk holding video frame `frame`."""
        for a, n in self.chunks:
            if a <= frame < a + n:
                return a, n
        raise IndexError(f"frame {frame} is not within 0..{self.full_shape[1] - 1}")

    def chunk(self, start: int, count: int) -> np.ndarray:
        """The read-only memmap (C, count, H, W, 3) of chunk [start, start + count), decoded on first use."""
        if start not in self._open:
            from stg_runtime.progress import progress_callback

            c, _, h, w, ch = self.full_shape
            key = self.key if (start, count) == (0, self.full_shape[1]) else dict(self.key, chunk=[start, count])
            label = f"decode frames {start}-{start + count - 1}"
            with progress_callback(label, enabled=self.show_progress) as report:
                self._open[start] = build_frame_cache(self.chunk_dir(start, count), key, (c, count, h, w, ch),
                                                      lambda arr: self.decoder.fill(arr, start, report))
        return self._open[start]

    def __getitem__(self, index):
        if not isinstance(index, tuple):
            index = (index,)
        if len(index) == 2 and index[0] == slice(None) and isinstance(index[1], slice):
            a, b, step = index[1].indices(self.count)
            if step != 1 or b <= a:
                raise IndexError(f"ChunkedFrames: only [:, a:b] views with a < b, got {index[1]}")
            view = self.with_options()
            view.start, view.count = self.start + a, b - a
            return view
        if len(index) >= 2 and all(isinstance(i, (int, np.integer)) for i in index[:2]):
            frame = int(index[1])
            if not 0 <= frame < self.count:
                raise IndexError(f"frame index {frame} out of range 0..{self.count - 1}")
            a, n = self.chunk_of(self.start + frame)
            return self.chunk(a, n)[(index[0], self.start + frame - a) + index[2:]]
        raise IndexError(f"ChunkedFrames: unsupported index {index!r} (use [c, f, ...] or [:, a:b])")

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_open"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _open={})


def common_frames(root, paths, labels, counts, sizes, num_frames: int | None = None) -> tuple[int, int, int]:
    """(num_frames, width, height) shared by every camera's frame source, or DataError naming the file.

    paths: each source's file or folder; labels: their short names (for listings); counts: their frame
    counts; sizes: their (width, height). Without num_frames all counts must be equal; with it, every
    source needs at least that many frames.
    """
    if num_frames is None:
        if len(set(counts)) > 1:
            listing = ", ".join(f"{lab}: {c} frames" for lab, c in zip(labels, counts))
            raise DataError(f"{root}: cameras have different frame counts ({listing}); use the first "
                            f"{min(counts)} with --frames {min(counts)} (num_frames= in Python)")
        num_frames = counts[0]
    else:
        short = [(path, c) for path, c in zip(paths, counts) if c < num_frames]
        if short:
            raise DataError(f"{short[0][0]}: has {short[0][1]} frames, fewer than the {num_frames} asked for")
    if len(set(sizes)) > 1:
        listing = ", ".join(f"{lab}: {w}x{h}" for lab, (w, h) in zip(labels, sizes))
        raise DataError(f"{root}: cameras have different frame sizes ({listing})")
    return num_frames, *sizes[0]


def file_signature(paths: Iterable[Path]) -> list:
    """[name, size, mtime_ns] of each file, for cache validation."""
    out = []
    for p in paths:
        st = Path(p).stat()
        out.append([str(p), st.st_size, st.st_mtime_ns])
    return out


def build_dataset(root: Path, layout: str, cameras: Sequence[Camera] | Callable[[int, int], Sequence[Camera]],
                  sources: Sequence[FrameSource], *, test_camera: str, downscale: int = 1, cache_dir=None,
                  num_frames: int | None = None, fps: float | None = None, default_fps: float = DEFAULT_FPS,
                  bounds=None, bounds_source: str = "layout", progress=None, signature: dict | None = None,
                  check: Callable[[], None] | None = None, lazy: bool = False) -> Dataset:
    """A Dataset from full-resolution cameras and their frame sources (same order), frames decoded into
    the frame cache <cache_dir or root/.stg_cache>/<layout>_<kind>_x<downscale>_f<num_frames>.

    cameras: the cameras, or a function of the frames' (width, height) that makes them (for layouts
    whose calibration is relative to the image size). Checks that every camera has the same number of
    frames (or at least num_frames) and that frames and cameras have one size, raising DataError naming
    the file. fps: used when given, else the first video's, else default_fps. bounds: (C, 2) near and
    far depth per camera, when the layout has them; bounds_source: where they come from (Dataset.bounds_source).
    signature: extra JSON-able cache key (e.g.
    calibration files). check: called before frames are decoded into a new cache (for costly
    consistency checks). progress(done, total): called per decoded frame. lazy: decode nothing now; the
    frames are a ChunkedFrames (one chunk, the whole video, until Dataset.chunked cuts it), `check` runs
    at once and `progress` is not called (ChunkedFrames' show_progress draws a bar per chunk instead).
    """
    if int(downscale) != downscale or downscale < 1:
        raise ValueError(f"downscale must be a positive integer, got {downscale}")
    downscale = int(downscale)
    probes = [probe(s) for s in sources]
    labels = [str(s.path.relative_to(root)) if s.path.is_relative_to(root) else str(s.path) for s in sources]
    num_frames, width, height = common_frames(root, [s.path for s in sources], labels,
                                              [c for c, _, _, _ in probes], [(w, h) for _, w, h, _ in probes],
                                              num_frames)
    if callable(cameras):
        cameras = cameras(width, height)
    names = [c.name for c in cameras]
    if test_camera not in names:
        raise DataError(f"{root}: no camera named {test_camera!r} to hold out (cameras: {', '.join(names)})")
    for cam, src in zip(cameras, sources):
        if (cam.width, cam.height) != (width, height):
            raise DataError(f"{src.path}: frames are {width}x{height} but camera {cam.name} is calibrated for "
                            f"{cam.width}x{cam.height}")
    out_w, out_h = width // downscale, height // downscale
    if out_w < 1 or out_h < 1:
        raise DataError(f"{root}: --downscale {downscale} leaves no pixels of its {width}x{height} frames")
    scaled = [replace(c, fx=c.fx / downscale, fy=c.fy / downscale, cx=c.cx / downscale, cy=c.cy / downscale,
                      width=out_w, height=out_h) for c in cameras]  # the camera model and distortion are kept
    if fps is None:
        fps = next((f for _, _, _, f in probes if f), None)
    fps = default_fps if fps is None else float(fps)
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")

    kind = "video" if sources[0].video is not None else "images"
    files = [f for s in sources for f in (s.files if s.video is not None else s.images[:num_frames])]
    key = {"layout": layout, "source": kind, "downscale": downscale, "num_frames": num_frames,
           "files": [[str(Path(p).relative_to(root)) if Path(p).is_relative_to(root) else p, size, mtime]
                     for p, size, mtime in file_signature(files)], **(signature or {})}
    shape = (len(scaled), num_frames, out_h, out_w, 3)

    decoder = FrameDecoder(list(sources), (width, height), (out_w, out_h))
    cache_root = Path(cache_dir) if cache_dir is not None else root / ".stg_cache"
    cache = cache_root / f"{layout}_{kind}_x{downscale}_f{num_frames}"
    if lazy:
        if check is not None:
            check()
        frames = ChunkedFrames(cache, key, shape, decoder)
        return Dataset(scaled, frames, fps, test_cameras=[names.index(test_camera)], bounds=bounds, path=root,
                       bounds_source=bounds_source)

    def fill(arr: np.ndarray) -> None:
        if check is not None:
            check()
        decoder.fill(arr, 0, progress)

    frames = build_frame_cache(cache, key, shape, fill)
    return Dataset(scaled, frames, fps, test_cameras=[names.index(test_camera)], bounds=bounds, path=root,
                   bounds_source=bounds_source)
