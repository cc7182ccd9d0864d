"""Method adapters: the reference model ``lmgs``, simplified CPU-trainable versions of the nine
compared methods (see ``design.md``), and ``external:NAME`` for frames rendered elsewhere.

Every adapter implements :class:`baselines.protocol.TalkingHead` and registers its factory
with :func:`baselines.protocol.register` when its module is imported. The toolkit finds them
through :data:`ADAPTERS`, the explicit table below: add a module here to add a method.
"""

ADAPTERS: tuple[str, ...] = (
    "baselines.lmgs_method",  # lmgs and its ablation / sweep variants
    "baselines.nerf",  # adnerf, radnerf, ernerf, geneface
    "baselines.gaussian",  # talkinggaussian, degstalk, gaussiantalker
    "baselines.twod",  # wav2lip, ip_lap
    "baselines.external",  # external:NAME
)
