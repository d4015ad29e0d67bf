"""The named choices of the settings, a module that imports nothing: the dataset readers, the
initialisation and the trainer take their lists from here, and so do the command lines' parsers.

The registries (LAYOUT_SPECS, SPLATTERS) name their code as "module:function" strings, imported only
where it is used, so that a new entry costs the command lines' --help nothing (docs/extending.md)."""

#: TrainConfig.motion_init values: the initial motion of the Gaussians (stg_train.data.flow).
MOTION_INITS = ("flow", "zero")
#: TrainConfig.init values: where the initial points come from (stg_train.data.points).
INIT_METHODS = ("auto", "sfm", "volume", "combined")
#: The dataset layouts, in detection order (raw data before the reference code's preprocessing, which writes
#: colmap_<i> folders beside it): name -> (reader, detector, what the detector looks for); the reader
#: (root, **options) -> Dataset and the detector (root) -> bool as "module:function" (stg_train.data.layouts).
LAYOUT_SPECS = {
    "n3v": ("stg_train.data.n3v:load_n3v", "stg_train.data.layouts:looks_like_n3v",
            "camXX.mp4 videos and poses_bounds.npy"),
    "technicolor": ("stg_train.data.technicolor:load_technicolor", "stg_train.data.layouts:looks_like_technicolor",
                    "<Scene>_undist_<frame>_<cam>.png images and cameras_parameters.txt"),
    "immersive": ("stg_train.data.immersive:load_immersive", "stg_train.data.layouts:looks_like_immersive",
                  "camera_NNNN.mp4 videos (or camera_NNNN/ frame folders) and models.json"),
    "reference": ("stg_train.data.reference:load_reference", "stg_train.data.layouts:looks_like_reference",
                  "colmap_0/, colmap_1/, ... each with images/camXX.png and sparse/0/"),
    "rig": ("stg_train.data.rig:load_rig", "stg_train.data.layouts:looks_like_rig",
            "images/<camera>/<frame>.png (or videos/<camera>.mp4) and a COLMAP model in sparse/0/"),
}
#: The splatter backends (TrainConfig.splatter, stg_train.render.rasterize): name -> "module:function" of
#: its rasterize(means, quats, scales, opacities, features, camera) -> RenderOutput.
SPLATTERS = {
    "numba": "stg_train.render.numba_splat:rasterize_numba",
    "torch": "stg_train.render.torch_splat:rasterize_torch",
    "gsplat": "stg_train.render.gsplat_backend:rasterize_gsplat",
}


def __getattr__(name: str):
    """LAYOUTS: the layouts' names, in detection order, as LAYOUT_SPECS holds them now."""
    if name == "LAYOUTS":
        return tuple(LAYOUT_SPECS)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
#: TrainConfig.segment_schedule values: how a long video's segments start (stg_train.warm).
SEGMENT_SCHEDULES = ("warm", "independent")
