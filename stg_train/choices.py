"""The named choices of the settings, a module that imports nothing: the dataset readers, the
initialisation and the trainer take their lists from here, and so do the command lines' parsers."""

#: TrainConfig.motion_init values: the initial motion of the Gaussians (stg_train.data.flow).
MOTION_INITS = ("flow", "zero")
#: TrainConfig.init values: where the initial points come from (stg_train.data.points).
INIT_METHODS = ("auto", "sfm", "volume", "combined")
#: The dataset layouts, in detection order (stg_train.data.layouts.READERS).
LAYOUTS = ("n3v", "technicolor", "immersive", "reference", "rig")
