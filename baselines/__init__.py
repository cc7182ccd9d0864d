"""Simplified, CPU-trainable versions of the nine compared methods (see ``design.md``).

Importing this package registers every adapter with :func:`lmgs_eval.methods.register`.
"""

from baselines import nerf  # noqa: F401  (registers adnerf, radnerf, ernerf, geneface)
from baselines import gaussian  # noqa: F401  (registers talkinggaussian, degstalk, gaussiantalker)
from baselines import twod  # noqa: F401  (registers wav2lip, ip_lap)
