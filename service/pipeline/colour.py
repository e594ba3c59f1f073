"""The colour stage: white balance and output space of one camera's frames, one for every output.

The JPEG preview and RTSP (both from the encoder's one tone map) and the EXR snapshot take a colour
frame's white balance and output space from here, so they agree: the preview's balance is the
automatic estimate smoothed over frame time (or the fixed multipliers), updated by the encoder
thread as it tone-maps (:meth:`ColourStage.preview_matrix`); a snapshot of a frame asks
:meth:`ColourStage.white_balance`, which gives the preview's smoothed balance while it is recent,
else the frame's own estimate (nobody watched, so nothing was smoothed). The EXR snapshot
(``service.publishers.snapshot``) takes the balance and the output space from here.
"""

from __future__ import annotations

import numpy as np

from service.pipeline.frames import Published
from svelive.whitebalance import ColourSettings, WhiteBalance, WhiteBalancer, output_matrix


class ColourStage:
    """White balance (fixed, or automatic smoothed over time), the optional camera -> Rec.709 matrix and the
    EXR output space of one camera. ``settings`` may be replaced at run time (a whole new ColourSettings).

    Mono frames have no colour: every method gives None for them.
    """

    def __init__(self, settings: ColourSettings) -> None:
        self.settings = settings
        #: updated by the encoder thread only (``preview_matrix``); its ``current`` is read by the others
        self._balancer = WhiteBalancer(settings)

    def preview_matrix(self, published: Published, settings: ColourSettings | None = None) -> np.ndarray | None:
        """Encoder thread, once per previewed frame: float32 (3, 3) camera RGB -> preview RGB (the white balance,
        the smoothed estimate updated with this frame, then the matrix); None for a mono frame."""
        image = published.hdr.image
        if image.ndim != 3:
            return None
        settings = settings or self.settings
        self._balancer.configure(settings)
        balance = self._balancer.update(image, published.hdr.host_time_ns)
        return output_matrix(balance.multipliers, settings.matrix)

    def white_balance(self, published: Published | None) -> WhiteBalance | None:
        """The white balance of ``published`` as the preview shows it (any thread); None for mono or no frame."""
        if published is None or published.hdr.image.ndim != 3:
            return None
        return self._balancer.for_frame(published.hdr.image, published.hdr.host_time_ns, self.settings)

    def public(self) -> dict:
        """The colour settings for /api/settings and /api/state (``ColourSettings.public``)."""
        return self.settings.public()
