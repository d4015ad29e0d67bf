"""stg_train: learn Spacetime Gaussians from multi-view video (torch). Depends on stg_runtime.

Importing it sets OMP_WAIT_POLICY=PASSIVE unless the environment already sets it (it must happen
before torch is first imported): torch's training steps are many small parallel regions, and
OpenMP threads that spin while waiting made each step up to 80x slower on a 2-core machine.
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
