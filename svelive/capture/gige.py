"""GigE Vision cameras through Aravis 0.8 (PyGObject), as ``gige[:DEVICE_ID]``.

DEVICE_ID is what ``arv-tool-0.8`` lists (e.g. ``Aravis-Fake-GV01``), a serial
number, or the camera's IP address; without one the first GigE camera found is
used, opened by its address. (Aravis's own "first camera" keeps the interface
whose broadcast the camera answered first, which need not be one the camera can
send to: a camera on 127.0.0.1 answers the broadcast of eth0 too, and its image
packets to eth0's address never leave it. By address, Aravis picks the interface
that routes to the camera.)

No image: when a connection delivers no frame within ``offline_after_s`` although
the camera answers on its control channel, the error names the camera, where its
image packets should go and what to try (open it by address, a firewall, the
packet size); on the first connection the iteration ends with that error (so
``svelive record`` says it within seconds), on later ones the source goes offline
with it and reconnects.

Receiving: a pool of ``n_buffers`` numpy arrays, each wrapped by
``Aravis.Buffer.new(size, address)`` so Aravis's stream thread writes packets
straight into numpy memory; the arrays live as long as the stream. A completed
buffer is decoded (:mod:`svelive.core.formats`) into the Frame's own array,
the one copy a frame gets, and the buffer goes straight back to the stream.
Packet resend is enabled explicitly (``packet-resend = ALWAYS``). A buffer whose
status is not SUCCESS (missing packets, timeout, size mismatch, ...) never
becomes a Frame: it is counted in ``stats()["drops"]`` under the status name
in lower case and re-queued.

Colour: a Bayer pixel format sets the frames' colour filter (``camera.cfa``) to
the layout its name gives, which GigE Vision's PFNC defines at the first pixel
of the delivered frame: the region offset does not shift it (colour cameras keep
offsets even or rename the format; Aravis's fake camera keeps the named phase at
odd offsets). ``cfa`` given as well must agree, ``cfa="none"`` is refused.

Liveness: when the device reports ``control-lost`` (heartbeat failure), or no
frame has come for ``offline_after_s`` (at least five frame periods), the source
reports offline, tears the stream down and reconnects with exponential backoff
(``backoff_s`` doubling up to ``backoff_max_s``) inside the same iteration,
reapplying the configuration. Frame ids stay increasing across reconnects and
GEV 1.x 16-bit block-id wraps.

``close()`` from another thread ends an iteration within ``poll_s`` (0.1 s)
while the camera streams; during a reconnection attempt to an absent camera the
iterating thread returns when Aravis gives up (about 1 s by name, 2.5 s by IP
address), while ``close()`` itself returns at once.

Teardown of a camera that vanished takes Aravis seconds (stopping acquisition,
freeing the stream and releasing the device each wait for GVCP timeouts: 12 s
measured against the fake camera), so it never runs under the device lock:
the stream, its buffers and the camera are detached under the lock and released
in a daemon thread, the stream before its arrays. ``close()`` waits for that at
most ``CLOSE_WAIT_S`` (a live camera takes milliseconds); a lost camera's is not
waited for at all, and the source goes on reconnecting.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from svelive.capture import build_sensor, make_config
from svelive.capture.source import Source
from svelive.core import formats
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor


def load_aravis() -> Any:
    """The Aravis 0.8 GI module, or a one-line SveliveError naming what to install."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise SveliveError(
            f"GigE needs Aravis 0.8 through PyGObject ({exc}); install the Debian packages gir1.2-aravis-0.8 "
            "libgirepository1.0-dev libcairo2-dev pkg-config and pip install 'PyGObject<3.51'") from None
    return Aravis


@dataclass(frozen=True)
class GigeConfig:
    """Camera settings (None leaves the camera's own value) and stream behaviour.

    Attributes:
        pixel_format: GenICam PixelFormat name, e.g. "Mono12Packed".
        width, height, offset_x, offset_y: region of interest in pixels.
        fps: acquisition frame rate, frames per second.
        exposure_us: exposure time in microseconds.
        gain_db: analog gain in dB.
        packet_size: GVSP packet size in bytes (None: negotiated automatically).
        n_buffers: buffers in the receive pool.
        packet_resend: ask the camera to resend lost packets.
        offline_after_s: no frame for this long (and at least 5 frame periods) means the camera
            is lost: the source reports offline and reconnects (0: never, for triggered cameras).
        reconnect: reconnect after the camera is lost (else the iteration ends with an error).
        backoff_s, backoff_max_s: first and largest wait between reconnection attempts.
    """

    pixel_format: str | None = None
    width: int | None = None
    height: int | None = None
    offset_x: int | None = None
    offset_y: int | None = None
    fps: float | None = None
    exposure_us: float | None = None
    gain_db: float | None = None
    packet_size: int | None = None
    n_buffers: int = 8
    packet_resend: bool = True
    offline_after_s: float = 1.5
    reconnect: bool = True
    backoff_s: float = 0.25
    backoff_max_s: float = 5.0


#: Longest ``close()`` waits for the device lock, then again for the teardown (seconds).
CLOSE_WAIT_S = 0.5

#: Stream counters kept (Aravis names), summed over connections.
STREAM_COUNTERS = ("n_completed_buffers", "n_failures", "n_underruns", "n_timeouts", "n_aborted",
                   "n_missing_frames", "n_size_mismatch_errors", "n_received_packets", "n_missing_packets",
                   "n_error_packets", "n_ignored_packets", "n_resend_requests", "n_resent_packets",
                   "n_duplicated_packets", "n_transferred_bytes")


class GigeSource(Source):
    """A GigE Vision camera; see the module docstring."""

    def __init__(self, spec: str, arg: str | None = None, *, pattern: str | None = None,
                 sensor: Sensor | None = None, bits: int | None = None, black_level: float | None = None,
                 white_level: float | None = None, cfa: str | None = None, **opts: Any) -> None:
        super().__init__(spec, pattern=pattern, sensor=sensor, cfa=cfa)
        self.config: GigeConfig = make_config(GigeConfig, opts, spec)
        if self.config.n_buffers < 2:
            raise SveliveError(f"{spec}: n_buffers must be >= 2")
        self.device_id = arg
        self._sensor_opts = (sensor, bits, black_level, white_level)
        self._aravis = load_aravis()
        self._io = threading.Lock()  # serialises device calls between _next and _close
        self._camera: Any = None
        self._stream: Any = None
        self._arrays: dict[Any, np.ndarray] = {}
        self._lost = threading.Event()
        self._counters = dict.fromkeys(STREAM_COUNTERS, 0)
        self._last_frame_t = 0.0
        self._next_attempt = 0.0
        self._backoff = self.config.backoff_s
        self._last_raw_id: int | None = None
        self._exposure: float | None = None  # ExposureTime last read back (us), stamped on every frame
        self._last_id: int | None = None
        self.camera_info: dict[str, Any] = {}
        self._found = ""  # the camera found when no id was given, for messages

    # ----- connection ------------------------------------------------------
    def _open(self) -> None:
        self._connect()

    def _open_camera(self) -> Any:
        """The Aravis camera for ``device_id``: by id, name or address, else by serial number; without
        an id, the first GigE camera found, opened by its address (see the module docstring)."""
        Ar = self._aravis
        target = self.device_id
        if not target:
            found = self._first_gige()
            if found is None:
                raise SveliveError(f"{self.spec}: no GigE camera found (arv-tool-0.8 lists the cameras Aravis "
                                   "sees; check the cable, the camera's power and its IP address)")
            target, self._found = found
        try:
            camera = Ar.Camera.new(target)
        except Exception as exc:  # GLib.Error or TypeError (None returned)
            camera = self._open_by_serial()
            if camera is None:
                what = f"GigE camera {self.device_id!r}" if self.device_id else f"the GigE camera {self._found}"
                raise SveliveError(f"cannot open {what}: {_message(exc)}") from None
        if camera is None:
            raise SveliveError(f"no GigE camera {self.device_id or ''} found".replace("  ", " "))
        return camera

    def _first_gige(self) -> tuple[str, str] | None:
        """(address, description) of the first GigE Vision camera Aravis finds, or None."""
        Ar = self._aravis
        try:
            Ar.update_device_list()
            for i in range(Ar.get_n_devices()):
                if Ar.get_device_protocol(i) == "GigEVision" and Ar.get_device_address(i):
                    described = (f"{Ar.get_device_vendor(i) or ''} {Ar.get_device_model(i) or ''}".strip()
                                 + f" (serial {Ar.get_device_serial_nbr(i)}, {Ar.get_device_address(i)})")
                    return Ar.get_device_address(i), described
        except Exception:  # noqa: BLE001 - reported by the caller as "no GigE camera found"
            return None
        return None

    def _connect(self) -> None:
        Ar = self._aravis
        c = self.config
        camera = self._open_camera()
        stream: Any = None
        arrays: dict[Any, np.ndarray] = {}
        try:
            self._configure(camera)
            self._exposure = float(camera.get_exposure_time()) if camera.is_exposure_time_available() else None
            pf_name = camera.get_pixel_format_as_string()
            self._format = formats.lookup(pf_name)
            # a Bayer format names the colour of the first delivered pixel, whatever the region offset
            # (PFNC; the fake camera keeps its phase at odd offsets too), so the layout is not shifted
            self._settle_camera(build_sensor(*self._sensor_opts, default_bits=self._format.bits), self._format.cfa,
                                self._format.name)
            self._pf_code = int(camera.get_pixel_format())
            payload = int(camera.get_payload())
            stream = camera.create_stream(None, None)
            if stream is None:
                raise SveliveError("could not create the stream")
            if isinstance(stream, Ar.GvStream):
                stream.set_property("packet-resend", Ar.GvStreamPacketResend.ALWAYS if c.packet_resend
                                    else Ar.GvStreamPacketResend.NEVER)
            for _ in range(c.n_buffers):
                arr = np.empty(payload, dtype=np.uint8)
                buf = Ar.Buffer.new(payload, arr.ctypes.data)
                arrays[buf] = arr
                stream.push_buffer(buf)
            device = camera.get_device()
            self._lost.clear()
            device.connect("control-lost", lambda *_: self._lost.set())
            camera.start_acquisition()
        except Exception as exc:
            # release the device now (the stream before its arrays): the traceback keeps this frame's
            # locals, and a camera object kept alive keeps the control channel from the next open
            _stop(camera)
            stream = None
            arrays = {}
            camera = None
            if isinstance(exc, SveliveError):
                raise
            raise SveliveError(f"{self.spec}: camera setup failed: {_message(exc)}") from None
        x, y, w, h = camera.get_region()
        info = {"device_id": camera.get_device_id(), "vendor": camera.get_vendor_name(),
                "model": camera.get_model_name(), "pixel_format": pf_name, "region": [x, y, w, h], "payload": payload}
        if camera.is_gv_device():
            try:
                info["address"] = _address(device.get_device_address())
                info["interface"] = _address(device.get_interface_address())
            except Exception:  # noqa: BLE001 - informative only
                pass
        del device
        with self._io:
            if self._closing.is_set():  # closed while connecting: drop what was built
                holder = [(camera, stream, arrays)]
                del camera, stream, arrays
                _dispose(holder, wait=0)
                return
            self._camera, self._stream, self._arrays = camera, stream, arrays
        self.camera_info = info
        self._offline_after = c.offline_after_s
        if c.offline_after_s and camera.is_frame_rate_available():
            try:  # at least five frame periods
                self._offline_after = max(c.offline_after_s, 5.0 / float(camera.get_frame_rate()))
            except Exception:  # noqa: BLE001 - a camera without a readable rate
                pass
        self._last_frame_t = time.monotonic()
        self._last_raw_id = None
        self._backoff = c.backoff_s
        self._set_online(True)

    def _open_by_serial(self) -> Any:
        """Open the camera whose serial number, physical id or address is ``device_id`` (None if none)."""
        Ar = self._aravis
        if not self.device_id:
            return None
        try:
            Ar.update_device_list()
            for i in range(Ar.get_n_devices()):
                keys = (Ar.get_device_serial_nbr(i), Ar.get_device_physical_id(i), Ar.get_device_address(i))
                if self.device_id in keys:
                    return Ar.Camera.new(Ar.get_device_id(i))
        except Exception:  # noqa: BLE001 - reported by the caller as "cannot open"
            return None
        return None

    def _configure(self, camera: Any) -> None:
        c = self.config
        if c.pixel_format is not None:
            available = list(camera.dup_available_pixel_formats_as_strings() or [])
            if c.pixel_format not in available:
                raise SveliveError(f"{self.spec}: pixel format {c.pixel_format!r} not offered by the camera; "
                                   f"it has {', '.join(available)}")
            formats.lookup(c.pixel_format)  # refuse formats we cannot unpack before streaming
            camera.set_pixel_format_from_string(c.pixel_format)
        if any(v is not None for v in (c.width, c.height, c.offset_x, c.offset_y)):
            x, y, w, h = camera.get_region()
            camera.set_region(c.offset_x if c.offset_x is not None else x, c.offset_y if c.offset_y is not None
                              else y, c.width or w, c.height or h)
        if c.fps is not None and camera.is_frame_rate_available():
            camera.set_frame_rate(float(c.fps))
        if c.exposure_us is not None and camera.is_exposure_time_available():
            camera.set_exposure_time(float(c.exposure_us))
        if c.gain_db is not None and camera.is_gain_available():
            camera.set_gain(float(c.gain_db))
        if c.packet_size is not None and camera.is_gv_device():
            camera.gv_set_packet_size(int(c.packet_size))

    # ----- exposure control ------------------------------------------------
    def exposure_time(self) -> float | None:
        """ExposureTime in microseconds, None while disconnected or on a camera without it."""
        with self._io:
            camera = self._camera
            try:
                if camera is None or not camera.is_exposure_time_available():
                    return None
                return float(camera.get_exposure_time())
            except Exception:  # noqa: BLE001 - GLib.Error from a lost device
                return None

    def set_exposure_time(self, value: float) -> float:
        """Set ExposureTime (microseconds, within the camera's bounds); returns the value read back."""
        with self._io:
            camera = self._camera
            if camera is None:
                raise SveliveError(f"{self.spec}: the camera is not connected; cannot set its exposure time")
            try:
                if not camera.is_exposure_time_available():
                    raise SveliveError(f"source {self.spec} cannot set its exposure time")
                lo, hi = camera.get_exposure_time_bounds()
                if not lo <= value <= hi:
                    raise SveliveError(f"{self.spec}: exposure time {value:g} us is outside the camera's "
                                       f"range {lo:g}..{hi:g} us")
                camera.set_exposure_time(float(value))
                self._exposure = float(camera.get_exposure_time())
                return self._exposure
            except SveliveError:
                raise
            except Exception as exc:  # noqa: BLE001 - GLib.Error
                raise SveliveError(f"{self.spec}: setting the exposure time failed: {_message(exc)}") from None

    def _detach(self) -> tuple[Any, Any, dict[Any, np.ndarray]]:
        """Take the camera, stream and arrays off the source (their counters added to the totals),
        for :func:`_dispose`. Holds self._io."""
        camera, stream, arrays = self._camera, self._stream, self._arrays
        self._camera = self._stream = None
        self._arrays = {}
        if stream is not None:
            for name in STREAM_COUNTERS:
                try:
                    self._counters[name] += int(stream.get_info_uint64_by_name(name))
                except Exception:  # noqa: BLE001 - a counter this Aravis lacks
                    pass
        return camera, stream, arrays

    def _close(self) -> None:
        if not self._io.acquire(timeout=CLOSE_WAIT_S):
            # a device call holds the lock (a camera timing out): tear down once it is free
            threading.Thread(target=self._close_later, name="svelive-gige-close", daemon=True).start()
            return
        try:
            holder = [self._detach()]
        finally:
            self._io.release()
        _dispose(holder, wait=CLOSE_WAIT_S)

    def _close_later(self) -> None:
        with self._io:
            holder = [self._detach()]
        _dispose(holder, wait=0)

    def _go_offline(self, reason: str) -> None:
        """The camera is lost: report why, release it in the background (its teardown waits for
        timeouts), and reconnect (or end with the reason). Holds self._io."""
        self._set_online(False, reason)
        _dispose([self._detach()], wait=0)
        if not self.config.reconnect:
            raise SveliveError(f"{self.spec}: camera lost ({reason})")
        self._next_attempt = time.monotonic()

    def _no_image(self, stall: float) -> str:
        """Why a connected camera delivers no frame: what it is, where its image packets should go,
        what arrived, and what to try (one line)."""
        info = self.camera_info
        stream = self._stream
        received = completed = 0
        if stream is not None:
            try:
                received = int(stream.get_info_uint64_by_name("n_received_packets"))
                completed = int(stream.get_info_uint64_by_name("n_completed_buffers"))
            except Exception:  # noqa: BLE001
                pass
        who = f"{info.get('vendor', '')} {info.get('model', '')}".strip() or "the camera"
        who += f" {info.get('device_id', '')}".rstrip() + (f" at {info['address']}" if info.get("address") else "")
        to = f" to {info['interface']}" if info.get("interface") else ""
        address = info.get("address")
        if received == 0:
            hint = (f"open it by address (gige:{address}), " if address and not self.device_id else "") \
                + "check that a firewall lets UDP from the camera in, and that its address and this " \
                  "interface are on one network"
            return (f"{self.spec}: {who} answers its control channel but sent no image packet{to} in "
                    f"{stall:.1f} s: {hint}")
        return (f"{self.spec}: {who}: {received} image packets arrived{to} in {stall:.1f} s but no frame completed "
                f"({completed}): lower packet_size (e.g. packet_size=1400) or the frame rate")

    def _try_reconnect(self) -> bool:
        now = time.monotonic()
        if now < self._next_attempt:
            self._wait(min(self._next_attempt - now, self.poll_s))
            return False
        try:
            self._connect()
        except SveliveError as exc:
            self._error = str(exc)
            self._next_attempt = time.monotonic() + self._backoff
            self._backoff = min(self._backoff * 2, self.config.backoff_max_s)
            return False
        self._reconnects += 1
        return True

    def _next(self) -> Frame | None:
        if self._stream is None:  # offline: one reconnection attempt, without holding the lock
            if self._closing.is_set() or not self._try_reconnect():
                return None
        with self._io:
            if self._closing.is_set() or self._stream is None:
                return None
            if self._lost.is_set():
                self._go_offline("control lost (no heartbeat reply)")
                return None
            buf = self._stream.timeout_pop_buffer(int(self.poll_s * 1e6))
            if buf is None:
                stall = time.monotonic() - self._last_frame_t
                if self._offline_after and stall > self._offline_after:
                    if self._last_raw_id is None:  # nothing on this connection: say why it cannot be
                        reason = self._no_image(stall)
                        if self._last_id is None:  # the first connection: nothing to reconnect to
                            self._set_online(False, reason)
                            _dispose([self._detach()], wait=0)
                            raise SveliveError(reason)
                        self._go_offline(reason)
                    else:
                        self._go_offline(f"no frame for {stall:.1f} s")
                return None
            try:
                return self._decode(buf)
            finally:
                self._stream.push_buffer(buf)

    def _decode(self, buf: Any) -> Frame | None:
        Ar = self._aravis
        host_ns = time.monotonic_ns()
        status = buf.get_status()
        if status != Ar.BufferStatus.SUCCESS:
            self._drop(status.value_nick.replace("-", "_"))
            return None
        if buf.get_payload_type() not in (Ar.BufferPayloadType.IMAGE, Ar.BufferPayloadType.EXTENDED_CHUNK_DATA):
            self._drop("not_image")
            return None
        if int(buf.get_image_pixel_format()) != self._pf_code:
            self._drop("pixel_format_mismatch")
            return None
        arr = self._arrays[buf]
        w, h = buf.get_image_width(), buf.get_image_height()
        x_pad, _ = buf.get_image_padding()
        stride = self._format.row_bytes(w) + x_pad if x_pad else None
        try:
            raw = formats.unpack(arr, w, h, self._format, stride, copy=True)
        except SveliveError:
            self._drop("size_mismatch")
            return None
        self._last_frame_t = time.monotonic()
        ts = int(buf.get_timestamp())
        # the time last applied: the frame in flight at a change is labelled with the new one
        return Frame(raw=raw, frame_id=self._unwrap(int(buf.get_frame_id())), host_time_ns=host_ns,
                     device_time_ns=ts if ts else None, pixel_format=self._format.name, camera=self.camera,
                     exposure_time=self._exposure)

    def _unwrap(self, raw_id: int) -> int:
        """Device frame id made monotonic across 16-bit wraps and reconnects."""
        if self._last_raw_id is None:
            fid = raw_id if self._last_id is None else self._last_id + 1
        else:
            d = raw_id - self._last_raw_id
            if d <= 0:  # GEV 1.x block ids run 1..65535 and wrap; anything else is a restart
                d = d + 65535 if self._last_raw_id <= 65535 and d > -65535 else 1
            fid = self._last_id + d  # type: ignore[operator]
        self._last_raw_id, self._last_id = raw_id, fid
        return fid

    def _extra_stats(self) -> dict[str, Any]:
        counters = dict(self._counters)
        stream = self._stream
        if stream is not None:
            for name in STREAM_COUNTERS:
                try:
                    counters[name] += int(stream.get_info_uint64_by_name(name))
                except Exception:  # noqa: BLE001
                    pass
        return {"stream": counters, "camera": dict(self.camera_info)}

    def stats(self) -> dict[str, Any]:
        """Base stats plus ``stream`` (Aravis counters) and ``camera``; ``drops`` adds ``underrun``."""
        out = super().stats()
        underruns = out["stream"].get("n_underruns", 0)
        if underruns:
            out["drops"]["underrun"] = underruns
            out["dropped"] += underruns
        return out


def _stop(camera: Any) -> None:
    """Stop acquisition, ignoring a camera that is already gone."""
    if camera is not None:
        try:
            camera.stop_acquisition()
        except Exception:  # noqa: BLE001 - GLib.Error from a lost device
            pass


def _address(address: Any) -> str:
    """Text of a Gio address (an InetSocketAddress's host, without the port)."""
    inner = getattr(address, "get_address", None)
    return (inner() if inner is not None else address).to_string()


def _release(holder: list) -> None:
    """Stop acquisition, then free the stream (its thread stops), then the arrays it wrote into."""
    camera, stream, arrays = holder.pop()
    _stop(camera)
    del stream  # the last reference: the stream's thread is joined here, before the arrays go
    del camera, arrays


def _dispose(holder: list, wait: float) -> None:
    """Release the ``(camera, stream, arrays)`` in ``holder`` (a one-item list holding the only
    references, from ``_detach``) in a daemon thread, waiting at most ``wait`` seconds: a camera that
    vanished takes Aravis seconds of timeouts to let go."""
    camera, stream, _ = holder[0]
    if camera is None and stream is None:
        return
    del camera, stream
    thread = threading.Thread(target=_release, args=(holder,), name="svelive-gige-release", daemon=True)
    thread.start()
    if wait > 0:
        thread.join(wait)


def _message(exc: BaseException) -> str:
    return getattr(exc, "message", None) or str(exc) or type(exc).__name__
