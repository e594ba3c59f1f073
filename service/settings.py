"""Service settings and where they come from: CLI > environment > config file > defaults.

Every setting has one name, used as the TOML/JSON key of the config file
(``--config PATH`` or ``SVELIVE_CONFIG``), as the environment variable
``SVELIVE_<NAME IN CAPITALS>`` and, with dashes, as the CLI option
(``--jpeg-quality``); the names are the fields of ServerSettings,
service.pipeline.PipelineConfig, svelive.tonemap.ToneSettings and svelive.whitebalance.ColourSettings.
``source_options`` is a table in the file and ``key=value,key=value`` in the environment and on the CLI;
``white_balance`` (``auto`` or three multipliers) and ``colour_matrix`` (9 numbers or ``none``) are arrays
in the file and comma-separated numbers in the environment and on the CLI.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import json
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from svelive.errors import SveliveError
from svelive.tonemap import ToneSettings
from svelive.whitebalance import ColourSettings, parse_colour_matrix, parse_white_balance

from service.pipeline import PipelineConfig

ENV_PREFIX = "SVELIVE_"
CONFIG_ENV = "SVELIVE_CONFIG"
MAX_TOKEN_LENGTH = 256


@dataclass(frozen=True)
class ServerSettings:
    """Where and for whom the HTTP server listens.

    Attributes:
        host, port: where to listen (127.0.0.1 unless told otherwise).
        token: bearer token required by every endpoint but /healthz; None: open.
        cors_origins: origins allowed by CORS; empty: no CORS headers at all.
        log_level: uvicorn log level.
        send_buffer_kb: kernel send buffer per client connection (KiB, Linux doubles it);
            bounds how much old video a slow client can have queued; 0: the system's autotuning.
    """

    host: str = "127.0.0.1"
    port: int = 8000
    token: str | None = None
    cors_origins: tuple[str, ...] = ()
    log_level: str = "info"
    send_buffer_kb: int = 256

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise SveliveError(f"port must be 0..65535, got {self.port}")
        if self.host != "localhost":
            try:
                ipaddress.ip_address(self.host)
            except ValueError:
                raise SveliveError(f"host must be an IP address or localhost, got {self.host!r}") from None
        if self.token is not None and not (1 <= len(self.token) <= MAX_TOKEN_LENGTH and self.token.isprintable()
                                           and " " not in self.token):
            raise SveliveError(f"token must be 1..{MAX_TOKEN_LENGTH} printable characters without spaces")
        if not 0 <= self.send_buffer_kb <= 65536:
            raise SveliveError(f"send buffer must be 0..65536 KiB, got {self.send_buffer_kb}")
        if self.log_level not in ("critical", "error", "warning", "info", "debug", "trace"):
            raise SveliveError(f"log level must be critical, error, warning, info, debug or trace, got {self.log_level!r}")


@dataclass(frozen=True)
class ServiceSettings:
    """Everything ``svelive serve`` can be told: the server's settings and the pipeline's.

    The flat setting names (config keys, ``SVELIVE_*`` variables, CLI options) are
    the field names of ServerSettings, PipelineConfig, ToneSettings and ColourSettings (see FIELDS).
    """

    server: ServerSettings = field(default_factory=ServerSettings)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)

    @classmethod
    def from_flat(cls, values: Mapping[str, Any]) -> ServiceSettings:
        """Build from flat names (every one optional)."""
        parts: dict[type, dict[str, Any]] = {owner: {} for owner in OWNERS}
        for name, value in values.items():
            parts[OWNER[name]][name] = value
        tone = ToneSettings(**parts[ToneSettings])
        colour = ColourSettings(**parts[ColourSettings])
        return cls(ServerSettings(**parts[ServerSettings]),
                   PipelineConfig(**parts[PipelineConfig], tone=tone, colour=colour))

    def public(self) -> dict[str, Any]:
        """The settings as a dict, the token masked."""
        out = dataclasses.asdict(self)
        out["server"]["token"] = None if self.server.token is None else "***"
        return out


#: the dataclasses whose fields are the settings (PipelineConfig's ``tone`` and ``colour`` are the last two)
OWNERS = (ServerSettings, PipelineConfig, ToneSettings, ColourSettings)
NESTED = ("tone", "colour")
#: flat setting name -> the dataclass that holds it; FIELDS: name -> dataclasses.Field
OWNER: dict[str, type] = {f.name: owner for owner in OWNERS for f in dataclasses.fields(owner) if f.name not in NESTED}
FIELDS = {f.name: f for owner in OWNERS for f in dataclasses.fields(owner) if f.name not in NESTED}


def parse_scalar(text: str) -> Any:
    """A config value given as text: int, float, true/false, or the text itself."""
    lowered = text.strip().lower()
    if lowered in ("true", "yes", "on"):
        return True
    if lowered in ("false", "no", "off"):
        return False
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text.strip()


def parse_options(text: str) -> dict[str, Any]:
    """``"fps=30,width=1920"`` -> {"fps": 30, "width": 1920}."""
    options: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise SveliveError(f"source option {item!r} is not KEY=VALUE")
        options[key.strip().replace("-", "_")] = parse_scalar(value)
    return options


def coerce(name: str, value: Any, where: str) -> Any:
    """``value`` (text from the environment or CLI, or a parsed config value) as the type of setting ``name``."""
    if value is None:
        return None
    kind = FIELDS[name].type
    try:
        if name == "source_options":
            if isinstance(value, str):
                return parse_options(value)
            if not isinstance(value, Mapping):
                raise ValueError("expected a table of options")
            return {str(k).replace("-", "_"): v for k, v in value.items()}
        if name == "white_balance":
            return parse_white_balance(value)  # SveliveError is a ValueError: reported below with ``where``
        if name == "colour_matrix":
            return parse_colour_matrix(value)
        if name == "cors_origins":
            items = value.split(",") if isinstance(value, str) else list(value)
            return tuple(item.strip() for item in items if str(item).strip())
        if "bool" in kind:
            parsed = parse_scalar(value) if isinstance(value, str) else value
            if not isinstance(parsed, bool):
                raise ValueError("expected true or false")
            return parsed
        if kind.startswith("int"):
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError("expected an integer")
            return int(value)
        if kind.startswith("float"):
            if isinstance(value, bool):
                raise ValueError("expected a number")
            return float(value)
        if isinstance(value, str) and value.strip() == "" and "None" in kind:
            return None
        if not isinstance(value, str):
            raise ValueError("expected text")
        return value.strip()
    except ValueError as exc:
        raise SveliveError(f"{where}: bad value {value!r} for {name} ({exc})") from None


def from_file(path: str | os.PathLike) -> dict[str, Any]:
    """Settings from a TOML (``.toml``) or JSON (``.json``) file; the ``[serve]`` table if there is one."""
    path = Path(path)
    if not path.is_file():
        raise SveliveError(f"config file {path} does not exist")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
        else:
            data = tomllib.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise SveliveError(f"config file {path}: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise SveliveError(f"config file {path}: expected a table of settings")
    data = data.get("serve", data)
    out = {}
    for key, value in data.items():
        name = str(key).replace("-", "_")
        if name not in FIELDS:
            raise SveliveError(f"config file {path}: unknown setting {key!r}; known: {', '.join(FIELDS)}")
        out[name] = coerce(name, value, f"config file {path}")
    return out


def from_env(environ: Mapping[str, str]) -> dict[str, Any]:
    """Settings from ``SVELIVE_<NAME>`` variables (empty ones are ignored)."""
    out = {}
    for name in FIELDS:
        value = environ.get(ENV_PREFIX + name.upper())
        if value is not None and value != "":
            out[name] = coerce(name, value, ENV_PREFIX + name.upper())
    return out


def resolve(cli: Mapping[str, Any] | None = None, environ: Mapping[str, str] | None = None,
            config: str | os.PathLike | None = None) -> ServiceSettings:
    """The effective settings: CLI values (None means "not given") over the environment over the file.

    The config file is ``config`` if given, else ``$SVELIVE_CONFIG`` if set, else none.
    """
    environ = os.environ if environ is None else environ
    merged: dict[str, Any] = {}
    config = config or environ.get(CONFIG_ENV) or None
    if config:
        merged.update(from_file(config))
    merged.update(from_env(environ))
    for name, value in (cli or {}).items():
        if value is not None:
            merged[name] = coerce(name, value, f"--{name.replace('_', '-')}")
    return ServiceSettings.from_flat(merged)
