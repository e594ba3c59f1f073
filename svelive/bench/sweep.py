"""One sweep of the stability suite: a difficulty axis and each setting's error along it (JSON-ready)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Sweep:
    """One sweep's curves."""

    name: str
    title: str
    axis: str
    error: str
    difficulty: list[float]
    errors: dict[str, list[float]] = field(default_factory=dict)
    log_y: bool = True
    notes: str = ""
