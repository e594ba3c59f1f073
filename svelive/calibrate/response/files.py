"""A response on disk: JSON written atomically (:func:`write_json`, :func:`save_response`) and read back
(:func:`load_response`) with one-line errors."""

from __future__ import annotations

import json
import os
from pathlib import Path

from svelive.core.atomic import write_bytes_atomic
from svelive.core.errors import SveliveError
from svelive.core.response import Response


def write_json(data: dict, path: str | os.PathLike) -> Path:
    """Write ``data`` as indented JSON, atomically (svelive.core.atomic)."""
    return write_bytes_atomic(path, (json.dumps(data, indent=2) + "\n").encode())


def save_response(response: Response, path: str | os.PathLike) -> Path:
    """Write ``response`` as JSON, atomically."""
    return write_json(response.to_dict(), path)


def load_response(path: str | os.PathLike) -> Response:
    """Read a response written by :func:`save_response` (``svelive calibrate response``)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise SveliveError(f"{path}: cannot read response file ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise SveliveError(f"{path}: not a response JSON file ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise SveliveError(f"{path}: a response file holds a JSON object")
    try:
        return Response.from_dict(data)
    except SveliveError as exc:
        raise SveliveError(f"{path}: {exc}") from None
