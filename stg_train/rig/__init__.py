"""The rig: what real cameras do to the picture, where they really are, and how a run finds out.

    camera_rig        CameraRig: the one object the Trainer asks about its cameras (set-up, the step's
                      correction of a render, their own Adam, checkpoint state)
    appearance        CameraAppearance: each camera's learned colour transform and vignetting
    lens              the lens falloff model 1 + k1 s + k2 s^2, s the squared radius over the corner's
    pose_refine       PoseCorrections: a learned rigid correction of each training camera's pose
    gauge             the similarity of the world that pictures cannot reveal, removed from the corrections
    self_calibration  the rig measured from its own pictures before training; "auto" decided from it
    remeasure         the rig measured again through the model's geometry, a third of the way through
    pose_align        a scored view's pose aligned to its own pictures (evaluation: stg-eval --align-poses)
    capture           the synthetic capture model (exposure, white balance, vignetting, noise, pose error)
                      and pose errors against a capture's truth

Nothing here is imported by stg_runtime: the exported `.stg` holds the canonical scene and the refined
cameras only. This package imports none of its modules: `stg-synth` takes the capture model without torch.
"""
