"""Recover the GelTip figure's contacts, and score both renderers on its real tiles.

Issue 52 item 4. The seed paper's figure shows, per column, a real GelTip tactile image
and the published fast model's simulation of the same contact with each of its four
light fields, all scaled down about 2.8 times (``real_contacts/README.md`` of the shared
data). The contacts' depth maps are not published; this study finds them back and
renders them with our reference and our fast path, against the real tile.

1. **Alignment.** A tile is a crop of the figure: tile pixel (row i, column j) is frame
   pixel (u, v) = (offset_u + scale j, offset_v + scale i) of the 640x480 frame
   (:class:`Alignment`). A frame image is brought to a tile by :func:`to_tile`: a
   Gaussian blur of sigma (scale - 1) / 2 frame px (scikit-image's anti-aliasing for
   a down-scale), then bilinear sampling. A tile's alignment is fitted
   (:func:`align`, Nelder-Mead, least mean |difference|) to a frame image of the same
   scene: the published tile to the published model's render, the real tile to the
   published real no-contact image (``real/bkg.png``), from the centred crop of the
   frame's height (scale H / h), the scale within SCALE_SLACK of that and the offsets
   within SHIFT_BOUND_PX frame px.
   The tiles are crops of a few px either way (measured: scale 2.82 on every tile that
   has a background, offsets -6 to +4 frame px); a centred resize instead leaves 3 to 8
   times the MAE on the linear tiles.
2. **The published model** (:class:`PaperModel`): their baked fields, prepared as
   ``studies.reproduce_published`` prepares them (blur, resize, rectification on the
   Sobel normals of their D_ref), with the paper dataset's settings (``NOTES.md``):
   Table 1's LEDs (the default spec's), i_a = 0.8, R.V not clamped, their D_ref
   (``sim_depth/bkg.npy``), and the tile's background: none (``nonebg``), the solid
   colour (``solidbg``) or the real no-contact image divided by 225 (``realbg``; the
   no-contact renders match the realbg tiles with 225, MAE 0.009-0.028, and not with
   255, 0.013-0.054), quantised to 8 bits as published (``to_8bit``).
3. **Recovery** (:func:`recover`), on the linear field's tile: the tap is the caption's
   object pressed by ``scenes.contact.press`` along the membrane's normal at the pixel
   (u, v) where the camera sees the contact point, ``depth`` deep, rolled by ``roll``
   about the normal (objects that are not round only). Their membrane mesh
   (``meshes/sensor/160x120_aligned_mesh.stl``, which ray-casts their D_ref to 0.008 mm
   median, ours to 0.038 mm) gives the point and normal. The search, on the tile's mean
   squared error over its pixels but a BORDER_PX frame (the figure's white gaps):

   * place: the centroid of the largest patch (by its sum of change; pixels
     PATCH_GAP_PX apart joined, so that an outline is one patch) where the tile differs
     from the model's no-contact render by more than CHANGE_LEVEL (mean over channels),
     inside the image circle less CIRCLE_MARGIN_PX (whose edge shows any crop error);
     then a coarse grid of COARSE_OFFSETS_PX (u and v) about it, and a refine within
     PLACE_BOUND_PX of it;
   * depth: COARSE_DEPTHS_MM, refined within DEPTH_BOUNDS_MM;
   * roll: COARSE_ROLLS steps over the object's symmetry period (ROLL_PERIOD_RAD, a
     full turn unless listed), refined within one step of the best;
   * the grid and a first bounded Nelder-Mead (``scipy.optimize``, REFINE_EVALUATIONS
     renders) on the tiles blurred by COARSE_BLUR_PX (thin outlines, such as the prism's
     in the linear tile, give a narrow basin otherwise), a second one on the sharp
     tiles; then the tile is aligned again to the recovered tap's render (the contact
     included) and the search refined once more (half the renders).

   How well it holds: per field, the MAE of the recovered tap's render against that
   field's tile (over the tile and over the contact, where the tile differs from the
   no-contact render by more than CHANGE_LEVEL, dilated by REGION_DILATION), beside the
   no-contact render's MAE; each field's tile is aligned to the recovered tap's render.
4. **Against the real tile** (:func:`score`): the recovered tap (pixel, depth, roll) is
   pressed on our membrane and rendered by the reference (``pbr``, default effects,
   ``--photons``) and by our fast path (``phong``, its default field), each with its
   own no-contact frame, both brought to the real tile by its alignment. The real
   no-contact image is the per-pixel median of the real tiles (README), each resampled
   onto the tile's pixels through their alignments (a median of crops cut a few px
   apart, as the README's top-left crop does, leaves the image circle's edge in every
   contact region: 4191 and 5048 px of columns 2 and 4, while it reproduces the
   README's numbers, mean change 0.028, 0.134, 0.148); with fewer than
   MIN_MEDIAN_TILES real tiles the published real no-contact image joins the median.
   The contact region is the README's: mean |tile - no-contact| over channels above
   CHANGE_LEVEL, dilated by REGION_DILATION px (``scenes.captures``), inside the image
   circle less a px. ``strength_ratio`` is ``scenes.image_stats.contact_strength`` of the
   simulation over the real tile's, over that region; ``shape_corr`` the Pearson
   correlation of the change images (each minus its own no-contact frame, signed, all
   channels) inside it. Both renderers are uncalibrated, so the ratio holds their
   exposure too: ``contrast`` splits it per channel into the level ratio (the no-contact
   images over the region: the camera's) and the relative-change ratio (the light's),
   and ``strength_ratio_exposed`` is the simulation seen through the real camera's
   exposure (:func:`exposure`: a gain per channel fitted on the no-contact tiles outside
   the contact region; a channel the real camera clipped over most of the tile, the
   GelTip's blue, is not judged); ``signed_ratio_exposed`` (:func:`signed_change`) is
   whether that change brightens or darkens the region as the real one does, which a
   strength (a mean of |change|) cannot tell. ``noise_strength`` is what the render's
   own Monte Carlo noise alone reads as strength there (:func:`noise_floor`), to tell a
   faint contact from noise.
5. **At the real contact's place** (``at_real_place``): the figure's real and simulated
   contacts of one column need not sit at one place in the frame, so each column is
   scored again with the recovered tap moved by the offset from the published tile's
   contact patch to the real tile's (each patch found as in step 3), its depth and roll
   kept: a translation of the pixel, not a fit to the real tile. Measured on the shared
   tiles: 6 frame px for column 0, but 72 (column 2) and 91 (column 4) frame px farther
   from the image's centre in the real tile than in the published simulation.
6. **Located on the real tile** (``at_real_place.located``): from that place, the fast
   path's render of the contact (its depth held) is moved, and rolled where the object is
   not round, until the magnitude of its change correlates best with the real tile's
   (:func:`locate`), and both renderers are scored there. This fits the place to the
   real tile, never the depth or the strength.

Run ``tactile-sim bench tiles --json PATH`` (``register``), or :func:`run`.

Modules: the tiles on disk (``disk``); tiles and frames (``frames``); the published
model (``paper``); recovery (``recovery``); against the real tile (``scoring``); both
renderers on a contact (``rendering``); located on the real tile (``locate``); the
benchmark (``bench``); the command (``cli``, which no module here imports). The names
below are re-exported for ``tests/test_tiles.py`` and callers of ``studies.tiles.X``.
"""

from .bench import PHOTONS, run
from .disk import (BACKGROUNDS, CAPTION, FIELDS, MATCH_FIELD, Column, TileError, discover, object_of, parse_objects,
                   read_tile)
from .frames import (CHANGE_LEVEL, Alignment, align, centred, change, changed_region, inner, largest_patch,
                     sample, tile_inside, to_tile)
from .locate import locate
from .paper import PaperModel, paper_spec, published
from .recovery import COARSE_DEPTHS_MM, Contact, Recovery, contact_centroid, match_report, recover, roll_period
from .rendering import image_noise, noise_floor, simulated
from .scoring import (CHANGE_VIEW_GAIN, change_figure, exposure, pearson, real_alignment, real_no_contact, score,
                      signed_change)

__all__ = ["Alignment", "BACKGROUNDS", "CAPTION", "CHANGE_LEVEL", "CHANGE_VIEW_GAIN", "COARSE_DEPTHS_MM", "Column",
           "Contact", "FIELDS", "MATCH_FIELD", "PHOTONS", "PaperModel", "Recovery", "TileError", "align", "centred",
           "change", "change_figure", "changed_region", "contact_centroid", "discover",
           "exposure", "image_noise", "inner", "largest_patch", "locate", "match_report", "noise_floor",
           "object_of", "paper_spec", "parse_objects", "pearson", "published", "read_tile", "real_alignment",
           "real_no_contact", "recover", "roll_period", "run", "sample", "score", "signed_change",
           "simulated", "tile_inside", "to_tile"]
