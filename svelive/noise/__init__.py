"""The noise model from the data (being cut into one module per job: svelive/noise/frame.py holds it all for now)."""

from svelive.noise.frame import *  # noqa: F401,F403
