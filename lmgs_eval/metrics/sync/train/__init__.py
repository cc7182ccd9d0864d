"""Training the bundled sync scorers: :mod:`.pixel` (with its corpus, :mod:`.pixel_data`) and :mod:`.landmark`.

Run as ``python -m lmgs_eval.metrics.sync.train.pixel`` / ``python -m lmgs_eval.metrics.sync.train.landmark``;
the recipe, seed and acceptance figures of the shipped weights are in ``../weights/*.json``.
"""
