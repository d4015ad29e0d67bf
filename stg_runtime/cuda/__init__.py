"""The GPU path of the runtime (numba.cuda), imported only when a GPU is asked for.

    device     is there a GPU (or numba's simulator), `require()`, CuPy when installed
    memory     device buffers: Workspace (kept between frames), device_empty, host/device inputs
    launch     kernel launches replayed without numba's per-call work
    minmax     dmin / dmax for kernels
    timeeval   time evaluation of a segment uploaded once (DeviceSegment)
    splat      the splatter, with stg_runtime.splat_cpu's contract (rasterize)
    sort       a device radix sort and scan, for when CuPy is not installed
    decoder    colour on the device: fused decoder, onnxruntime decoder, lite and SH colour

The projection, the time evaluation and the SH colour are written once at the package's top level
(stg_runtime.projection, timeeval, sh) and compiled for both targets. docs/gpu.md describes the path
and its requirements, docs/performance.md its measured speed.
"""
