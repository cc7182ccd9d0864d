"""NeRF family: AD-NeRF, RAD-NeRF, ER-NeRF and GeneFace, simplified onto one small volume renderer.

All four share :class:`NeRFHead` (a conditioned radiance field) and :func:`render_rays`
(volume rendering inside the head's bounding box, composited over the frame's background,
as the field's protocol does with the torso over ``bc.jpg``). They differ only where the
originals differ:

* ``adnerf`` (Guo et al., ICCV 2021): an MLP on the positional encoding of the point,
  with the smoothed per-frame audio feature concatenated to its input.
* ``radnerf`` (Tang et al., 2022): a decomposed audio-spatial encoding: multi-resolution
  dense 3D grids for the point and a 2D grid indexed by a learned 2D projection of the
  audio feature; no region attention.
* ``ernerf`` (Li et al., ICCV 2023): the tri-plane hash encoder of :mod:`lmgs` for the
  point and region attention (channel gates from the spatial feature) over the audio.
* ``geneface`` (Ye et al., ICLR 2023): audio -> 68 3D landmarks (the project's per-subject
  predictor) -> an MLP NeRF conditioned on the landmarks (their whitened PCA coefficients).

Volume rendering (:mod:`baselines.nerf.rays`) is that of NeRF (Mildenhall et al., 2020):
stratified samples between the entry and exit of the head box, composited over the background.

Rendering a trained field (no autograd) marches the same samples in groups along each ray
(:func:`march_rays`): a ray stops once its transmittance is below ``1e-4`` (what it would
still add is below a 40th of a uint8 level), and ER-NeRF and RAD-NeRF skip samples in cells
of their occupancy grid (:meth:`NeRFHead.update_occupancy`) where no training condition put
density, as the originals' occupancy-grid ray marching does. AD-NeRF and GeneFace have no
occupancy grid (neither original does).

Modules: :mod:`.rays` (camera rays, the box test, :func:`render_rays` and :func:`march_rays`),
:mod:`.field` (:class:`NeRFHead` and its encoders), :mod:`.methods` (the budget and the four
adapters, registered when this package is imported).
"""

from baselines.nerf.field import NeRFHead
from baselines.nerf.methods import NeRFBudget, NeRFMethod  # importing it registers the adapters
from baselines.nerf.rays import box_hits, camera_rays, march_rays, render_rays

__all__ = ["NeRFBudget", "NeRFHead", "NeRFMethod", "box_hits", "camera_rays", "march_rays", "render_rays"]
