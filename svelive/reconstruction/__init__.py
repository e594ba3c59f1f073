"""Reconstruction: raw SVE frames (with their camera) in, HDR frames out.

The public names are re-exported by :mod:`svelive`: ``reconstruct`` and
``methods`` (single frames, :mod:`.single`), ``Reconstructor`` and
``reconstruct_sequence`` (streams, :mod:`.stream`); ``methods`` is not re-exported
here, where the name is the subpackage's (``import svelive.reconstruction.methods.adaptive``
must find the package, not the function). The modules:

- ``input``: the camera applied to a raw frame (response, black level,
  exposures, censoring, colour channels) -> ``SveInput``;
- ``methods/``: one module per method, a registry declaring each one's capabilities;
- ``colour``: colour mosaics, jointly (luminance and channel ratios) or split per channel;
- ``single``: the single-frame API, confidence and predicted variance;
- ``stream``: the per-stream Reconstructor;
- ``consistency``, ``fusion`` (with ``config`` and ``numerics``): the motion tests;
- ``warmup``: compiles every kernel a stream can run.
"""

from svelive.reconstruction.single import reconstruct
from svelive.reconstruction.stream import Reconstructor, SequenceResult, reconstruct_sequence
from svelive.reconstruction.warmup import warm_up

__all__ = ["reconstruct", "Reconstructor", "SequenceResult", "reconstruct_sequence", "warm_up"]
