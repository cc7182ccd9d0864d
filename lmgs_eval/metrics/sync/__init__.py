"""Lip sync (LSE-D, LSE-C, the AV offset): the scorers, their weights, and how a run picks one.

* :mod:`.maths`: syncnet_python's MFCC, windows and distances; :mod:`.scoring`: LSE of one clip
  with a scorer (``lse``) or with the scorers of a ``--sync`` choice (the registry's ``lse`` metric);
  :mod:`.check`: the self-check every LSE carries;
* :mod:`.crops`: face boxes and syncnet_python's face crops (:class:`~.crops.FaceClip`: one clip's
  crops and landmarks, each found once);
* :mod:`.pixel` and :mod:`.landmark`: the two kinds of scorer; :mod:`.nets`: their torch networks
  (importing the official weights, exporting the bundled one); :mod:`.scorers`: finding, loading and
  hash-checking them (the bundled ones' files in ``weights/``);
* :mod:`.select`: ``--sync`` and what ``auto`` tries; :mod:`.probe`: ``lmgs-eval sync-check``'s figures;
* :mod:`.train`: how the bundled scorers were trained.

Nothing is imported here: each module is imported by its own path.
"""
