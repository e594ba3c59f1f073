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
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.pipeline import PipelineConfig
from svelive.core.errors import SveliveError
from svelive.tonemap import ToneSettings
from svelive.whitebalance import ColourSettings, parse_colour_matrix, parse_white_balance

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
        token_file: file holding the token (its first line); read at start-up, so the token
            never shows in ``ps``. Exclusive with ``token``.
        allowed_hosts: host names (besides the bound address and, on loopback, localhost) the
            ``Host`` header may name: the names users reach this server by.
        header_timeout_s: a connection whose request headers are not complete this long after
            it opened (or after its previous response) is closed.
        max_connections: open connections beyond this are refused.
        rtsp_port: serve every camera's preview as H.264 over RTSP on this port (``/cam/NAME``, the
            first camera also ``/live``); 0: no RTSP.
        metrics_public: serve /metrics without the token (for a Prometheus that cannot send one).
    """

    host: str = "127.0.0.1"
    port: int = 8000
    token: str | None = None
    cors_origins: tuple[str, ...] = ()
    log_level: str = "info"
    send_buffer_kb: int = 256
    token_file: str | None = None
    allowed_hosts: tuple[str, ...] = ()
    header_timeout_s: float = 10.0
    max_connections: int = 512
    rtsp_port: int = 0
    metrics_public: bool = False

    def __post_init__(self) -> None:
        if self.token_file is not None:
            if self.token is not None:
                raise SveliveError("give the token or a token file, not both")
            object.__setattr__(self, "token", read_token_file(self.token_file))
            object.__setattr__(self, "token_file", None)  # read once: the settings hold the token itself
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
        if not 0.5 <= self.header_timeout_s <= 300:
            raise SveliveError(f"header timeout must be 0.5..300 s, got {self.header_timeout_s}")
        if not 8 <= self.max_connections <= 65536:
            raise SveliveError(f"max connections must be 8..65536, got {self.max_connections}")
        if not 0 <= self.rtsp_port <= 65535 or (self.rtsp_port and self.rtsp_port == self.port):
            raise SveliveError(f"RTSP port must be 0 (off) or 1..65535 and not the HTTP port, got {self.rtsp_port}")
        for name in self.allowed_hosts:
            if not name or len(name) > 253 or any(c in name for c in " /@?#"):
                raise SveliveError(f"allowed host {name!r} is not a host name")
        if self.log_level not in ("critical", "error", "warning", "info", "debug", "trace"):
            raise SveliveError(f"log level must be critical, error, warning, info, debug or trace, got {self.log_level!r}")


def read_token_file(path: str) -> str:
    """The token in ``path``: its first line, stripped; a one-line error if the file cannot give one."""
    try:
        with open(path, encoding="utf-8") as f:
            token = f.readline(MAX_TOKEN_LENGTH + 2).strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise SveliveError(f"token file {path}: {getattr(exc, 'strerror', None) or exc}") from None
    if not token:
        raise SveliveError(f"token file {path} is empty")
    return token


@dataclass(frozen=True)
class ServiceSettings:
    """Everything ``svelive serve`` can be told: the server's settings and the pipeline's.

    The flat setting names (config keys, ``SVELIVE_*`` variables, CLI options) are
    the field names of ServerSettings, PipelineConfig, ToneSettings and ColourSettings (see FIELDS).
    """

    server: ServerSettings = field(default_factory=ServerSettings)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    cameras: tuple[tuple[str, PipelineConfig], ...] = ()

    def named_pipelines(self) -> dict[str, PipelineConfig]:
        """Every camera to serve, by name, in order: the config file's camera list, or the one pipeline."""
        return dict(self.cameras) if self.cameras else {DEFAULT_CAMERA: self.pipeline}

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


#: Name of the camera when the service runs one pipeline without a camera list.
DEFAULT_CAMERA = "main"
#: What a camera's name may be: it is a URL path segment (``/cam/NAME/``) and a metrics label.
CAMERA_NAME = re.compile(r"[a-z0-9][a-z0-9_-]{0,31}")


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
        if name in ("cors_origins", "allowed_hosts"):
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


def read_config(path: str | os.PathLike) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Settings from a TOML (``.toml``) or JSON (``.json``) file -- the ``[serve]`` table if there is
    one -- and its camera list (``[[cameras]]`` tables, each with a ``name`` and pipeline settings)."""
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
    cameras = data.pop("cameras", None)
    data = data.get("serve", data)
    if cameras is None and isinstance(data, dict):
        cameras = data.pop("cameras", None)
    if not isinstance(data, dict):
        raise SveliveError(f"config file {path}: [serve] must be a table of settings")
    out = settings_table(data, f"config file {path}")
    if cameras is None:
        return out, []
    if not isinstance(cameras, list) or not cameras or not all(isinstance(c, dict) for c in cameras):
        raise SveliveError(f"config file {path}: cameras must be a list of tables ([[cameras]] in TOML)")
    tables = []
    for index, table in enumerate(cameras):
        where = f"config file {path}, camera {index + 1}"
        table = dict(table)
        name = table.pop("name", None)
        if not isinstance(name, str) or not CAMERA_NAME.fullmatch(name):
            raise SveliveError(f"{where}: name must be 1..32 lower-case letters, digits, - or _ "
                               f"(it is a URL path), got {name!r}")
        if any(t["name"] == name for t in tables):
            raise SveliveError(f"{where}: the name {name!r} is used twice")
        values = settings_table(table, f"{where} ({name})")
        server_names = sorted(n for n in values if OWNER[n] is ServerSettings)
        if server_names:
            raise SveliveError(f"{where} ({name}): {', '.join(server_names)} belong to the server, not to a camera")
        tables.append({"name": name, **values})
    return out, tables


def settings_table(data: Mapping[str, Any], where: str) -> dict[str, Any]:
    """A table of settings with its values coerced; an unknown name is a one-line error."""
    out = {}
    for key, value in data.items():
        name = str(key).replace("-", "_")
        if name not in FIELDS:
            raise SveliveError(f"{where}: unknown setting {key!r}; known: {', '.join(FIELDS)}")
        out[name] = coerce(name, value, where)
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

    The config file is ``config`` if given, else ``$SVELIVE_CONFIG`` if set, else none. With a camera
    list in the file, each camera's table sits between the file's top level and the environment:
    a setting given on the command line or in the environment applies to every camera, except
    ``source`` and ``source_options``, which only a camera's table can give.
    """
    environ = os.environ if environ is None else environ
    merged: dict[str, Any] = {}
    cameras: list[dict[str, Any]] = []
    config = config or environ.get(CONFIG_ENV) or None
    if config:
        file_values, cameras = read_config(config)
        merged.update(file_values)
    given = from_env(environ)
    for name, value in (cli or {}).items():
        if value is not None:
            given[name] = coerce(name, value, f"--{name.replace('_', '-')}")
    merged.update(given)
    settings = ServiceSettings.from_flat(merged)
    if not cameras:
        return settings
    per_camera_only = sorted({"source", "source_options"} & set(given))
    if per_camera_only:
        raise SveliveError(f"{', '.join(per_camera_only)} given on the command line or in the environment, but "
                           f"config file {config} lists cameras: set them in each [[cameras]] table")
    base = {k: v for k, v in merged.items() if OWNER[k] is not ServerSettings}
    named = []
    for table in cameras:
        own = {k: v for k, v in table.items() if k != "name"}
        values = {**base, **own, **{k: v for k, v in given.items() if OWNER[k] is not ServerSettings}}
        named.append((table["name"], ServiceSettings.from_flat(values).pipeline))
    return dataclasses.replace(settings, pipeline=named[0][1], cameras=tuple(named))
