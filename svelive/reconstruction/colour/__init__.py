"""Colour SVE: a mosaic of colour filters and exposures in, linear camera RGB out.

Every pixel i reads s_i = e_i L_c(i) (plus noise): its exposure times the
radiance of its own colour channel c(i). Two ways to reconstruct (``mode``):

``"split"``, the baseline the issue asks for: HDR per colour channel with a
monochrome method, then demosaicing. The frame is split into its CFA-phase
sub-images (for a CFA of same-colour blocks, such as quad-RGGB, into sub-images
of whole blocks, so that each keeps the block's exposures), each with its own
sub-pattern of exposures (RGGB + ``1/1/8/8`` gives four quarter images with the
pattern ``1/8``); the method reconstructs each, the results go back to their
pixels as an HDR mosaic, and the mosaic is demosaiced. OpenCV demosaics only 8-
and 16-bit data, so the mosaic is log-encoded to 16 bits (log2 of radiance plus
the longest exposure's noise floor, over the frame's range: a step of well under
0.1 % of a value), demosaiced, and decoded: interpolating log radiance suits HDR
data, where linear interpolation across an edge of a thousand to one smears the
bright side over the dark (measured on the shipped crops, dual-ISO at bright
exposure: up to 1 dB PU21 better than linear-domain bilinear interpolation,
nowhere worse by more than 0.05 dB). A Bayer CFA goes through OpenCV's
edge-aware conversion (``COLOR_Bayer...2RGB_EA``).
A CFA that is not a 2x2 Bayer tile (quad-RGGB, custom tiles) has no OpenCV
demosaicing: there each channel is interpolated by normalised convolution with a
separable tent as wide as the CFA's period (bilinear for Bayer), in the same log
encoding. No noise model and no highlight rule beyond the mono method's.

``"joint"``, the default: colour is the low-resolution part of the problem,
luminance the full-resolution part, and the noise model serves both.

(a) Chroma. Over the cells of the joint tile (exposure pattern and CFA: 4x2
for dual-ISO, 4x4 for quad-Bayer), each channel's uncensored readings x = s / e
are averaged with inverse-variance weights e_k^2 / (e_k L0 / g + sigma^2) of
the noise model at a pilot L0 (the channel's shot-noise estimate sum s / sum e
in the cell), then smoothed over the 3x3 neighbouring cells ([1, 2, 1] / 4 each
way) weighted by the share of each cell's information its uncensored readings
hold (1 without censoring), the smallest over its channels, so that every
channel of a cell weighs alike (per channel, a small light whose red and green
clipped spread its measured blue into the black cells around: violet). Not by the cells' information itself: evaluated at
each cell's own pilot it is larger for darker cells (1 / L in the shot-noise
regime), which biased every edge towards its dark side and cost 2 dB PU21.
Each channel's cell value stands for the centroid of its samples in the cell
(weights e, the shot-limited ones) and is moved to the cells' centres by
bilinear interpolation over the cells: without that, channels sampled half a
cell apart read different points of any edge, which is false colour at every
neutral edge. At the centres, L = sum_c n_c C_c (n_c the channel's share of the
CFA tile: 1/4, 1/2, 1/4 for Bayer) and the shares k_c = C_c / L. The same
shares from each cell's own readings alone (unsmoothed, centred alike) hold
colour finer than 3x3 cells: the smoothed shares move towards them by the
garrote of (b') below where the two differ beyond their noise (the variance of
own - smoothed is v_own - v_smoothed for nested estimates; the evidence is the
3x3 cells' mean squared difference), so bright scenes keep fine colour and the
dark keeps the smoothed shares. Where a
share's deviation from a neutral surface's is within its noise over the 3x3
cells (the colour noise of dark regions), it is shrunk towards the neutral by
the same garrote: noise in the dark is not painted as colour (5 stops
dim, dual-ISO, mean of the shipped crops: CIEDE2000 mean 8.6 -> 7.8, p99
21.7 -> 20.4; PU21 on luminance unchanged). Last, each channel's shares take
the median of the 3x3 cells around, and are scaled back to sum_c n_c k_c = 1.
A cell whose channels read different sides of an edge (its samples sit at
different places in the cell, and the centring and smoothing shift each
channel's profile of the edge differently) has shares that neither side has:
up to twice the neutral's at a black/white edge, and the luminance folded with
them alternated from pixel to pixel along the edge (zipper). Among its
neighbours such a cell is an outlier, and a median rejects it while it keeps
an edge between two colours (a straight edge keeps the majority of the 3x3
cells on each side); colour features narrower than two cells go. Measured
(neutral black/white edge of docs/stability.md, luminance error within 3 px at
2 stops): dual-ISO 0.150 -> 0.036 stop (split 0.061), column-Bayer 0.156 ->
0.041 (0.062), assorted-4x4 0.151 -> 0.067 (0.077), quad-Bayer 0.193 -> 0.045
(0.247). All of
this is computed at cell resolution and interpolated bilinearly on the fly by
the compiled passes below (no full-resolution chroma planes are written).

(b) Luminance as a monochrome SVE problem. Pixel i reads
s_i = e_i L_c = (e_i k_c) Y where the chroma is right: the mosaic is a
monochrome SVE frame of the luminance Y = sum_c n_c L_c whose effective
exposure e'_i = e_i k_c(i) varies per pixel (SveInput.folded). The signal is
the raw signal, so censoring and the Poisson-Gaussian noise model hold as
they are; the chosen mono method (``adaptive`` by default) reconstructs Y at
full resolution with its own rules for noise, edges, censoring and lower
bounds. Where the chroma is locally wrong (a colour edge inside the chroma's
support), one channel's readings disagree with their neighbours beyond their
noise, and ``adaptive`` keeps each pixel's own reading there, as at any edge.
A method that reads only the pattern's tile (MethodSpec.exposures is False:
``aggregate``) gets the readings divided by k_c instead, exact below
saturation, approximate at it.

(b') Refinement at the chroma's scale (methods that report their variance).
The cells also give a coarse luminance L with a small variance; the fine Y is
moved towards it by a noise-model garrote (:func:`refine`) where the two differ
by no more than Y's noise: in the read-noise regime a full-resolution estimate
is mostly noise, and the mono method's window alone averages too few readings
there (on the shipped crops 5 stops dim, +0.7 to +1.9 dB PU21 on the two
noise-limited scenes, -0.6 dB on the third, within 0.3 dB at bright exposure).

(c) RGB = Y k_c for each channel c, with the same k_c as the folding (so at a
pixel whose own reading decided Y, its own channel is that reading).

(c'') Saturated colour (single frames, 2x2 Bayer CFAs): where a pixel's own
channel holds under 10 % of its brightest channel's share (blended up to 30 %),
its reading says next to nothing about Y, which is then the mono method's
interpolation over readings of the other channels; there its other channels
come from their own lattices (log-bilinear over the 3x3), as a demosaicing
does, so that fine detail of a saturated colour survives
(svelive.reconstruction.colour.lattice; docs/peers.md: BrightRings +1.5 to
+2.1 dB PU21 over all channels, no shared frame lower).

(c''') Small clipped lights (single frames, any CFA): a light under two cells
on a side that clips the long exposure is found from its readings (sites at
least 2 stops and 5 noise deviations over their CFA phase's local median,
joined to a censored reading), and where its readings are flat within their
noise, it takes one colour pooled from all its sites instead of the cells'
(which saw a few sites of some colours each: blue, green or red lights), by a
garrote on that colour's noise (svelive.reconstruction.colour.lights).

Highlights. Where a channel has censored readings in a cell, its uncensored
neighbours are the darker ones, so the cell keeps its own readings (at least
their bound); where it has censored readings and no uncensored one, its value
is only a lower bound, and a clipped channel kept at its bound beside measured
ones is what makes clipped highlights magenta or pink (green, the most
sensitive channel, clips first). So such a channel is raised to at least the
white-balanced level of the brightest measured channel of the cell,
max(bound, white_c max_m C_m / white_m): a highlight that clipped some channels
goes neutral (white), never magenta; a saturated colour whose measured channels
are darker keeps its bound. Where every channel is censored, all take the
neutral white at the largest bound (white_c max_m bound_m / white_m), and the
mono method flags Y as a lower bound there. The white balance is the median,
over about 4096 cells whose smoothed luminance is measured to 10 % (an SNR of
10 by the noise model) and away from channels with only censored readings, of
C_R / C_G and C_B / C_G: robust to coloured objects; used for highlights and as
the neutral of the chroma's garrote. (Choosing cells by each channel's own SNR
favoured cells where that channel read high: 10 % too red and blue on a dark
grey frame. Too few cells, or none where a 64x exposure clips over a whole
bright ground, left it at 1, 1, 1: highlights went magenta.)

Known limit: the chroma is that of cells (4x2 pixels for dual-ISO), so colour
that changes within a few pixels (thin coloured lines, fine colour texture)
is folded with the cells' shares, and the luminance there inherits their
error: with the true shares of every pixel the luminance would be about 2 dB
PU21 better on the shared images at bright exposure. On a neutral edge the
zipper is gone (above); at 1 stop of contrast on assorted-4x4 the luminance
error near the edge is still 0.074 stop against the baseline's 0.062.

Units: radiance in DN at relative exposure 1 per channel (before white
balance); the luminance Y in that unit, which ``variance`` and
``lower_bound`` of the result describe.

The modules, one job each: ``run`` (:func:`run_colour`, the public entry), ``split_baseline`` (the baseline),
``cells`` (the cells' layout and per-cell statistics), ``highlights`` (the white balance and the rules for
censored and clipped channels), ``shares`` (step a), ``interpolate`` (from cells to pixels),
``folding`` (steps b and c: e' = e k_c, RGB = Y k_c), ``refinement`` (step b'), ``lattice`` (step c''),
``lights`` (step c'''),
``sites`` (opt-in chroma per site on Bayer CFAs, after step c) and ``joint_parts`` (the joint
reconstruction and its parts).
"""

from svelive.reconstruction.colour.cells import CellLayout, cell_layout
from svelive.reconstruction.colour.folding import colourise, folded_exposure, luminance_input
from svelive.reconstruction.colour.highlights import WHITE_CELLS, WHITE_MIN_CELLS, WHITE_SNR, white_balance
from svelive.reconstruction.colour.interpolate import PIECE_ROWS, Interpolation, interpolation
from svelive.reconstruction.colour.joint_parts import Joint, fold_luminance, joint
from svelive.reconstruction.colour.lattice import lattice_channels
from svelive.reconstruction.colour.lights import light_colours
from svelive.reconstruction.colour.refinement import refine
from svelive.reconstruction.colour.run import MODES, run_colour
from svelive.reconstruction.colour.shares import COARSE_NONE, SHARE_FLOOR, Chroma, chroma, partial_chroma
from svelive.reconstruction.colour.split_baseline import demosaic, split

__all__ = ["COARSE_NONE", "MODES", "PIECE_ROWS", "SHARE_FLOOR", "WHITE_CELLS", "WHITE_MIN_CELLS", "WHITE_SNR",
           "CellLayout", "Chroma", "Interpolation", "Joint", "cell_layout", "chroma", "colourise", "demosaic",
           "fold_luminance", "folded_exposure", "interpolation", "joint", "lattice_channels", "light_colours",
           "luminance_input",
           "partial_chroma", "refine", "run_colour", "split", "white_balance"]
