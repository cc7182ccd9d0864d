"""lmgs: landmark-guided 3D Gaussian Splatting talking heads.

The model library. It knows tensors, cameras, audio features and its own configs; it never
imports :mod:`lmgs_eval` (folder layouts, metrics and results files live there).
"""

__version__ = "0.1.0"
