"""stg_train: learn Spacetime Gaussians from multi-view video (torch). Depends on stg_runtime.

Importing it sets OMP_WAIT_POLICY=PASSIVE unless the environment already sets it (it must happen
before torch is first imported): torch's training steps are many small parallel regions, and OpenMP
threads that spin while waiting make them many times slower on a machine with few cores
(docs/performance.md).
"""
import os
import sys
import warnings

if "torch" in sys.modules and "OMP_WAIT_POLICY" not in os.environ:
    warnings.warn("stg_train was imported after torch, so OMP_WAIT_POLICY=PASSIVE cannot take effect: CPU "
                  "training may be many times slower. Import stg_train first, or set OMP_WAIT_POLICY=PASSIVE "
                  "in the environment.", RuntimeWarning, stacklevel=2)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
