"""Compiled per-pixel kernels: the one way svelive compiles Python loops (numba).

The methods and the motion stage are chains of per-pixel arithmetic between a
few window sums. Done as numpy operations each link reads and writes whole
arrays, so a frame costs tens of passes over memory; a kernel fuses a chain
into one pass. Window sums stay with OpenCV (``methods.base.smooth``), which
vectorises them better than a loop would.

Rules for a kernel (what makes LLVM vectorise it, and keeps it thread-safe):
- decorate it with :data:`kernel`; it releases the GIL, so strips of one frame
  run in parallel on the caller's threads (no numba threading of its own,
  which would oversubscribe the two cores the service shares with OpenCV);
- loop over flat, C-contiguous float32 arrays (``flat``), write into outputs
  the caller allocates, and keep constants float32 (``np.float32(...)``): a
  float64 literal turns the whole chain into float64;
- no raising: the numpy error model gives inf/nan on division by zero, as numpy does.

The first call of a kernel compiles it (about a second); ``cache=True`` keeps the
machine code on disk (``__pycache__`` or ``$NUMBA_CACHE_DIR``), so later
processes load it in milliseconds.
"""

from __future__ import annotations

from functools import partial

import numba
import numpy as np
from numba import types
from numba.extending import intrinsic

#: Decorator of every compiled kernel: no GIL, cached on disk, numpy's division semantics.
kernel = partial(numba.njit, nogil=True, cache=True, error_model="numpy")


def flat(*arrays: np.ndarray) -> list[np.ndarray]:
    """1-D views of C-contiguous arrays (a copy only for a non-contiguous one), for kernels that loop once."""
    return [a.reshape(-1) for a in arrays]


@intrinsic
def fma32(typingctx, a, b, c):
    """a b + c rounded once (float32), inside kernels: where a kernel must round as other code does (OpenCV's
    vectorised filters and resizes take a fused multiply-add per tap); numba itself never fuses."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return types.float32(types.float32, types.float32, types.float32), codegen
