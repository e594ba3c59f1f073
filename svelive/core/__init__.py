"""The ground floor: the values every other part of svelive passes around (camera, exposure pattern, colour
filter, sensor, frame, inverse response, raw pixel formats), errors and atomic file writes. Every module may
import these; they import nothing of the project outside this package."""
