"""The protocols: each says what to run; :mod:`lmgs_eval.runner` says how.

* :mod:`~lmgs_eval.protocols.self_driven`: train on the training split, drive with the test
  split's audio, score against its ground truth (Table I).
* :mod:`~lmgs_eval.protocols.cross`: drive trained models with other audio (Table II).
* :mod:`~lmgs_eval.protocols.calibration`: the ground truth against negative controls.
* :mod:`~lmgs_eval.protocols.plate`: the "GT head on plate" reference row.
* :mod:`~lmgs_eval.protocols.stress`: perturbed driving audio (:mod:`~lmgs_eval.protocols.perturb`).
* :mod:`~lmgs_eval.protocols.capacity`: quality and cost against the Gaussian budget.
"""
