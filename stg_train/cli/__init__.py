"""The trainer's command lines, each a thin parser over one library call:

    train     stg-train    stg_train.pipeline.train / run_demo
    eval      stg-eval     stg_train.metrics.evaluate_player on a dataset's held-out camera
    synth     stg-synth    stg_train.synthetic.write_n3v
    convert   stg-convert  stg_train.convert (compress, import-reference, import-3dgs, export-ply, merge)
"""
