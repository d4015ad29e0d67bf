"""Segments of a long video trained in parallel: on a Ray cluster (`stg-train --ray`, stg_train.distributed.ray)
or on the GPUs of one machine (`stg-train --gpus`, stg_train.distributed.local).

Both run each segment of stg_train.segments' plan as one job (stg_train.distributed.job): an ordinary
segment run (stg_train.pipeline.train) into OUT/segments/NN, which continues from the segment's last
checkpoint when it is run again, so a job retried after its worker died resumes where that worker's
last checkpoint left it. The driver prepares the segments and merges and evaluates them as a local run
does (stg_train.pipeline.prepare_segments, finish_segments) and shows one progress display for the
whole job (stg_train.distributed.board). Ray is imported only by stg_train.distributed.ray (the
`distributed` extra).
"""


class DistributedError(Exception):
    """A parallel run that cannot start or finish (no Ray, storage not shared, a segment that failed
    on every try); the message says what and what to do."""
