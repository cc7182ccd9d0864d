"""lmgs: landmark-guided 3D Gaussian Splatting talking heads.

The model library. It knows tensors, cameras, audio features and its own configs; it never
imports :mod:`lmgs_eval` (folder layouts, metrics and results files live there).
"""

import os as _os

# torch and numba each run an OpenMP pool; with the default (active) wait policy the idle
# pool spins on the cores the other one needs. On 2 cores that made a training step 5x
# slower (22.4 s vs 4.7 s for 200 steps, measured). Must be set before torch loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
