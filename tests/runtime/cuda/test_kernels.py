"""Every kernel of stg_runtime.cuda (splat, sort choice, time evaluation, decoders) and
Player(device="cuda") against the float64 oracle (stg_runtime.spec), the CPU player and onnxruntime's
decoder.

Without a GPU the kernel tests run in numba's CUDA simulator, which must be enabled before numba.cuda is
first imported: test_kernels_under_simulator runs this file again in a subprocess with
NUMBA_ENABLE_CUDASIM=1 on tiny images (the simulator runs every GPU thread in Python). On a machine where
numba sees a GPU the same tests run directly, on larger scenes, and the subprocess test is skipped.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from stg_runtime import Camera, Player
from stg_runtime.cuda import device
from stg_runtime.cuda import splat as splat_cuda
from stg_runtime.cuda.memory import Workspace
from stg_runtime.demo import demo_model, random_model
from stg_runtime.spec import rasterize_oracle

from tests.scenes import clean_scenes

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
GPU = device.gpu_available()
RUN = SIM or GPU
needs_kernels = pytest.mark.skipif(not RUN, reason="no GPU here: these run in the simulator subprocess "
                                                   "(test_kernels_under_simulator)")
needs_gpu = pytest.mark.skipif(not GPU, reason="needs a real CUDA GPU")
TOL = 1e-4
W, H = (16, 12) if SIM else (96, 64)  # the simulator is slow: tiny images
M = 30 if SIM else 400


def _scene(seed, m, channels, **kwargs):
    (scene,) = clean_scenes(seed, 1, m, W, H, channels, **kwargs)
    return scene


def _assert_matches(got, ref):
    f, a, d = got
    rf, ra, rd = ref
    assert f.dtype == a.dtype == d.dtype == np.float32
    assert f.shape == rf.shape and a.shape == ra.shape and d.shape == rd.shape
    np.testing.assert_allclose(f, rf, atol=TOL, rtol=0)
    np.testing.assert_allclose(a, ra, atol=TOL, rtol=0)
    solid = ra > 0.5
    assert np.all(np.abs(d - rd)[solid] <= TOL * np.maximum(1.0, rd[solid]))
    assert ra.max() > 0.5  # the scene shows something


@needs_kernels
@pytest.mark.parametrize("channels, seed, tile_size, kwargs", [
    (3, 0, 16, {}),
    (9, 1, 8, {}),
    (3, 2, 8, {"opacity": (0.02, 0.3), "size": (2.0, 10.0)}),  # deep: many thin layers per pixel
    (3, 7, 16, {"opacity": (0.6, 1.0), "size": (2.0, 10.0)}),  # opaque: pixels stop (T < 1e-4)
    (17, 3, 16, {"opacity": (0.6, 1.0), "size": (1.0, 8.0)}),  # more channels than one pass holds
    (3, 10, 16, {"fisheye": 190}),  # a fisheye wider than a hemisphere
])
def test_kernels_match_oracle(channels, seed, tile_size, kwargs):
    arrays, camera, ref = _scene(seed, M, channels, **kwargs)
    got = splat_cuda.rasterize(*arrays, camera, tile_size=tile_size)
    _assert_matches(got, ref)


@needs_kernels
def test_equal_depths_composite_lower_index_first():
    arrays, camera, _ = _scene(8, M // 2, 3, opacity=(0.5, 0.9))
    means, quats, scales, opacities, features = arrays
    twice = [np.concatenate([a, a]) for a in (means, quats, scales, opacities)]
    twice.append(np.concatenate([features, -features]))  # the copies differ only in colour
    ref = rasterize_oracle(*twice, camera)
    got = splat_cuda.rasterize(*twice, camera)
    _assert_matches(got, ref)
    swapped = rasterize_oracle(*twice[:4], np.concatenate([-features, features]), camera)
    assert np.abs(swapped[0] - ref[0]).max() > 0.1  # the order of the tied pairs shows in the image


@needs_kernels
def test_device_inputs_outputs_and_tile_size():
    from numba import cuda
    arrays, camera, ref = _scene(4, M, 9)
    on_device = [cuda.to_device(a) for a in arrays]
    f, a, d = splat_cuda.rasterize(*on_device, camera, tile_size=16, out="device")
    assert device.is_device_array(f) and f.shape == (H, W, 9)
    _assert_matches((f.copy_to_host(), a.copy_to_host(), d.copy_to_host()), ref)
    # Every per-pixel decision is the pixel's own: the tiling changes nothing, bit for bit.
    f5, a5, d5 = splat_cuda.rasterize(*arrays, camera, tile_size=5)
    np.testing.assert_array_equal(f5, f.copy_to_host())
    np.testing.assert_array_equal(a5, a.copy_to_host())
    with pytest.raises(ValueError, match="tile_size"):
        splat_cuda.rasterize(*arrays, camera, tile_size=64)


@needs_kernels
def test_device_sorts_agree():
    """CuPy's sort and cuda.sort's radix sort give the same image, bit for bit (on a GPU with CuPy)."""
    arrays, camera, ref = _scene(9, M, 3, opacity=(0.3, 0.9))
    with pytest.raises(ValueError, match="sort must be one of"):
        splat_cuda.rasterize(*arrays, camera, sort="bitonic")
    if device.cupy() is None:
        with pytest.raises(RuntimeError, match="CuPy is not installed"):
            splat_cuda.rasterize(*arrays, camera, sort="cupy")
        return
    with_cupy = splat_cuda.rasterize(*arrays, camera, sort="cupy")
    with_numba = splat_cuda.rasterize(*arrays, camera, sort="numba")
    for a, b in zip(with_cupy, with_numba):
        np.testing.assert_array_equal(a, b)
    _assert_matches(with_numba, ref)


@needs_kernels
def test_stage_seconds_times_each_step_without_changing_the_image():
    arrays, camera, ref = _scene(6, M, 3)
    plain = splat_cuda.rasterize(*arrays, camera)
    with splat_cuda.stage_seconds() as seconds:
        timed = splat_cuda.rasterize(*arrays, camera)
        splat_cuda.rasterize(*arrays, camera)
    assert list(seconds) == ["inputs", "project", "depth order", "tile keys", "tile sort", "ranges", "composite"]
    assert all(s > 0 for s in seconds.values())
    before = dict(seconds)
    splat_cuda.rasterize(*arrays, camera)  # outside the block: nothing added
    assert seconds == before
    for a, b in zip(plain, timed):
        np.testing.assert_array_equal(a, b)
    _assert_matches(timed, ref)


@needs_kernels
def test_workspace_keeps_its_buffers_and_changes_nothing_in_the_images():
    ws = Workspace()
    small = _scene(11, M // 3, 3)
    big = _scene(12, M, 3, size=(4.0, 12.0))  # at tile_size 2 many more tile entries: the key buffer grows
    capacity = []
    for (arrays, camera, ref), tile_size in ((small, 16), (big, 2), (small, 16)):
        got = splat_cuda.rasterize(*arrays, camera, tile_size=tile_size, workspace=ws, out="device")
        host = tuple(a.copy_to_host() for a in got)
        _assert_matches(host, ref)
        for a, b in zip(host, splat_cuda.rasterize(*arrays, camera, tile_size=tile_size)):  # fresh buffers
            np.testing.assert_array_equal(a, b)
        capacity.append(ws.buffer("ids", (1,), np.int32, at_least=True).shape[0])
    assert capacity[0] < capacity[1] == capacity[2]  # grown once, then kept
    again = splat_cuda.rasterize(*small[0], small[1], workspace=ws, out="device")
    assert again[0] is got[0]  # the same buffers: the next call overwrites them
    arrays, camera, ref = _scene(13, M, 9)  # another channel count: a new features buffer
    _assert_matches(splat_cuda.rasterize(*arrays, camera, workspace=ws), ref)


@needs_kernels
def test_player_cuda_follows_a_moving_camera_and_time():
    """One player, a new camera and time every frame (the camera and time reach the kernels by value:
    on a GPU these are replayed launches with new scalars, see stg_runtime.cuda.launch)."""
    from stg_runtime.cuda import launch as cuda_launch
    from stg_runtime.camera import orbit
    model = random_model(M, "full", width=W, height=H, radius_px=(1.0, 6.0))
    cameras = orbit(model.cameras, 3)
    times = [0.1 * model.duration, 0.6 * model.duration, 0.9 * model.duration]
    cuda_player, cpu_player = Player(model, device="cuda"), Player(model, device="cpu")
    for camera, t in zip(cameras + cameras[:1], times + times[:1]):
        got = cuda_player.render_all(camera, t)
        want = cpu_player.render_all(camera, t)
        for name, g, w in zip(got._fields, got, want):
            np.testing.assert_allclose(g, w, atol=TOL, rtol=0, err_msg=f"{name} at t = {t}")
        assert want.alpha.max() > 0.2
    if GPU and cuda_launch._dispatcher_module() is not None:
        assert cuda_launch._prepared  # the launches were recorded (and replayed)


@needs_kernels
def test_empty_and_culled_scenes_render_transparent():
    arrays, camera, _ = _scene(5, M, 3)
    means, quats, scales, opacities, features = arrays
    f, a, d = splat_cuda.rasterize(means, quats, scales, np.zeros_like(opacities), features, camera)
    assert f.shape == (H, W, 3) and not f.any() and not a.any() and not d.any()
    f, a, d = splat_cuda.rasterize(means[:0], quats[:0], scales[:0], opacities[:0], features[:0], camera)
    assert f.shape == (H, W, 3) and not a.any()


def _other_decoder(seed=0, hidden=8):
    """A 12 -> hidden -> 3 decoder graph: allowed by the format, not fused."""
    from stg_runtime.onnx_mlp import mlp_to_onnx
    rng = np.random.default_rng(seed)
    return mlp_to_onnx([rng.normal(0, 0.5, (hidden, 12)).astype(np.float32),
                        rng.normal(0, 0.5, (3, hidden)).astype(np.float32)])


@needs_kernels
def test_device_decoders_match_onnxruntime_on_the_host():
    from numba import cuda

    from stg_runtime.decoder import OnnxDecoder
    from stg_runtime.cuda.decoder import FusedDecoder, OnnxDeviceDecoder
    segment = demo_model("full", num_frames=2).segments[0]
    arrays, camera, _ = _scene(6, M, 9)
    features = splat_cuda.rasterize(*arrays, camera)[0] * 3.0  # larger features: the ReLUs matter
    features_d = cuda.to_device(features)
    want = OnnxDecoder(segment.decoder, segment.activation)(features, camera)
    assert want.std() > 0.01
    onnx = OnnxDeviceDecoder(segment.decoder, segment.activation)  # the fused decoder's reference
    np.testing.assert_allclose(onnx(features_d, camera).copy_to_host(), want, atol=1e-6, rtol=0)
    fused = FusedDecoder.from_onnx(segment.decoder, segment.activation)
    assert fused is not None
    np.testing.assert_allclose(fused(features_d, camera).copy_to_host(), onnx(features_d, camera).copy_to_host(),
                               atol=1e-5, rtol=0)
    # Other graph shapes are not fused; onnxruntime runs them.
    other = _other_decoder()
    assert FusedDecoder.from_onnx(other, "sigmoid") is None
    np.testing.assert_allclose(OnnxDeviceDecoder(other, "clamp")(features_d, camera).copy_to_host(),
                               OnnxDecoder(other, "clamp")(features, camera), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="expects 9 feature channels, got 6"):
        onnx(cuda.to_device(np.zeros((2, 3, 6), np.float32)), camera)
    # Fisheye cameras: the kernels' pixel rays (projection.pixel_ray) are the host's (Camera.ray_directions).
    fish = Camera(camera.fx / 2, camera.fy / 2, camera.cx, camera.cy, W, H, camera.world_to_camera,
                  model="fisheye", distortion=(0.05, -0.01, 0.002, -5e-4))
    want = OnnxDecoder(segment.decoder, segment.activation)(features, fish)
    assert np.abs(want - OnnxDecoder(segment.decoder, segment.activation)(features, camera)).max() > 1e-3
    np.testing.assert_allclose(onnx(features_d, fish).copy_to_host(), want, atol=1e-6, rtol=0)
    np.testing.assert_allclose(fused(features_d, fish).copy_to_host(), want, atol=1e-5, rtol=0)


@needs_kernels
def test_sh_colours_match_oracle():
    from numba import cuda

    from stg_runtime.camera import Camera
    from stg_runtime.cuda.decoder import sh_colours
    from stg_runtime.spec import sh_colours_oracle
    rng = np.random.default_rng(3)
    means = rng.normal(size=(40, 3)).astype(np.float32)
    means[0] = [0.5, -1.0, 2.0]  # at the camera centre: the zero direction
    R = Camera.look_at((0, 0, 0), (1, 2, 3), (0, -1, 0), 60, W, H).R
    camera = Camera(50, 50, W / 2, H / 2, W, H, np.block([[R, -R @ np.array([[0.5], [-1.0], [2.0]])], [0, 0, 0, 1]]))
    np.testing.assert_allclose(camera.center, [0.5, -1.0, 2.0], atol=1e-12)
    for k in (1, 4, 9, 16):
        coeffs = rng.normal(0, 2.0, (40, 3 * k)).astype(np.float32)
        got = sh_colours(cuda.to_device(coeffs), cuda.to_device(means), camera).copy_to_host()
        want = sh_colours_oracle(coeffs, means, camera.center)
        np.testing.assert_allclose(got, want, atol=1e-5, rtol=1e-6, err_msg=f"K = {k}")
        assert (want == 0).any() and (want > 0.5).any()  # some colours clamp at 0
    with pytest.raises(ValueError, match="not an SH layout"):
        sh_colours(cuda.to_device(np.zeros((2, 9), np.float32)), cuda.to_device(means[:2]), camera)


@needs_gpu
def test_onnxruntime_cuda_provider_decoder_on_gpu():
    """Where onnxruntime-gpu is installed, OnnxDeviceDecoder runs on the device buffers."""
    from numba import cuda

    from stg_runtime.decoder import OnnxDecoder
    from stg_runtime.cuda.decoder import OnnxDeviceDecoder, cuda_provider_available
    if not cuda_provider_available():
        pytest.skip("onnxruntime without its CUDA provider (the onnxruntime-gpu package)")
    arrays, camera, _ = _scene(10, M, 9)
    features = splat_cuda.rasterize(*arrays, camera)[0] * 3.0
    other = _other_decoder(4)
    decoder = OnnxDeviceDecoder(other, "sigmoid")
    assert decoder.on_device
    np.testing.assert_allclose(decoder(cuda.to_device(features), camera).copy_to_host(),
                               OnnxDecoder(other, "sigmoid")(features, camera), atol=1e-5, rtol=0)


def test_bound_session_run_matches_plain_run():
    """The IOBinding call the CUDA provider path makes, on host buffers with the CPU provider (the same
    binding; only the device type differs)."""
    from stg_runtime.decoder import OnnxDecoder
    from stg_runtime.cuda.decoder import run_bound
    decoder = OnnxDecoder(_other_decoder(3), "sigmoid")
    rows = np.random.default_rng(2).normal(size=(50, 12)).astype(np.float32)
    out = np.full((50, 3), np.nan, np.float32)
    run_bound(decoder, "cpu", rows.ctypes.data, 50, out.ctypes.data)
    (want,) = decoder.session.run(None, {decoder.input_name: rows})
    np.testing.assert_allclose(out, want, atol=1e-6, rtol=0)


@needs_kernels
@pytest.mark.parametrize("kind", ["lite", "full"])
def test_time_evaluation_matches_cpu(kind):
    from stg_runtime.timeeval import evaluate
    from stg_runtime.cuda.timeeval import DeviceSegment
    segment = random_model(4 * M, kind, width=W, height=H).segments[0]
    segment.t_scale[::3] = 300.0  # a third of them are visible briefly only
    device_segment = DeviceSegment(segment)
    for tau in (0.0, 0.37, 1.0):
        want = evaluate(segment, tau)
        got = [a.copy_to_host() for a in device_segment.evaluate(tau)]
        assert 0 < len(want.index) < segment.count  # some Gaussians are faded out at every time
        kept = got[3] >= np.float32(1 / 255)
        np.testing.assert_array_equal(np.flatnonzero(kept), want.index)
        for name, g, w in zip(("means", "quats", "scales", "opacities", "features"), got, want[1:]):
            np.testing.assert_allclose(g[kept], w, atol=1e-6, rtol=1e-6, err_msg=f"{name} at tau={tau}")


@needs_kernels
@pytest.mark.parametrize("kind", ["lite", "full", "sh", "full-unfused"])
def test_player_cuda_matches_cpu(kind):
    model = random_model(M, kind.split("-")[0], width=W, height=H, radius_px=(1.0, 6.0))
    if kind == "full-unfused":  # a 12 -> 8 -> 3 decoder: not fused, run by onnxruntime
        model.segments[0].decoder = _other_decoder(1)
    camera = model.cameras[0]
    cuda_player = Player(model, device="cuda")
    assert cuda_player.device == "cuda"
    got = cuda_player.render_all(camera, 0.5 * model.duration)
    want = Player(model, device="cpu").render_all(camera, 0.5 * model.duration)
    for name, g, w in zip(got._fields, got, want):
        assert isinstance(g, np.ndarray) and g.dtype == np.float32, name
        np.testing.assert_allclose(g, w, atol=TOL, rtol=0, err_msg=name)
    assert want.alpha.max() > 0.5
    if kind.startswith("full"):  # which decoder path ran
        from stg_runtime.cuda.decoder import FusedDecoder, OnnxDeviceDecoder
        ran = type(cuda_player._device_decoders[id(model.segments[0])])
        assert ran is (OnnxDeviceDecoder if kind == "full-unfused" else FusedDecoder)
    rgb = cuda_player.render(camera, 0.5 * model.duration, out="device")
    assert device.is_device_array(rgb)
    np.testing.assert_allclose(rgb.copy_to_host(), want.rgb, atol=TOL, rtol=0)


@needs_kernels
def test_player_cuda_crossfades_like_cpu():
    """A crossfade (format 1.3) on the GPU: the two segments' renders blended, host and device outputs."""
    from dataclasses import replace

    from stg_runtime.model import Model
    a, b = (random_model(M, "full", seed=s, width=W, height=H, radius_px=(1.0, 6.0)) for s in (0, 1))
    model = Model("full", a.fps, [a.segments[0], replace(b.segments[0].retimed(50, 50), crossfade_frames=4)],
                  cameras=a.cameras)
    camera, t = model.cameras[0], 49 / model.fps  # B's weight 3/8
    cuda_player, want = Player(model, device="cuda"), Player(model, device="cpu").render_all(camera, t)
    for name, g, w in zip(want._fields, cuda_player.render_all(camera, t), want):
        np.testing.assert_allclose(g, w, atol=TOL, rtol=0, err_msg=name)
    rgb = cuda_player.render(camera, t, out="device")
    assert device.is_device_array(rgb)
    np.testing.assert_allclose(rgb.copy_to_host(), want.rgb, atol=TOL, rtol=0)


@needs_kernels
def test_auto_never_picks_the_simulator():
    assert Player(demo_model("lite", num_frames=2), device="auto").device == ("cuda" if GPU else "cpu")


@needs_gpu
def test_player_cuda_renders_demo_on_gpu():
    model = demo_model("full", num_frames=4)
    camera = model.cameras[0]
    got = Player(model, device="cuda").render(camera, 0.05)
    want = Player(model, device="cpu").render(camera, 0.05)
    np.testing.assert_allclose(got, want, atol=TOL, rtol=0)


def test_cuda_without_gpu_is_refused_clearly():
    if RUN:
        pytest.skip("the kernels can run here")
    with pytest.raises(RuntimeError, match="no CUDA GPU.*device='cpu'"):
        Player(demo_model("lite", num_frames=2), device="cuda")
    assert Player(demo_model("lite", num_frames=2), device="auto").device == "cpu"
    with pytest.raises(ValueError, match="needs device 'cuda'"):
        Player(demo_model("lite", num_frames=2), device="cpu").render(demo_model("lite").cameras[0], 0.0, out="device")


def test_kernels_under_simulator(run_under_simulator):
    if RUN:
        pytest.skip("the kernels run directly in this process")
    run_under_simulator(__file__, passed=24)
