"""``Camera`` on OpenCV: a V4L2 device (path or index, ``CAP_V4L2``) or a stream URL
(``CAP_FFMPEG``).

Freshness: a grabber thread reads frames continuously and keeps only the newest one
with its arrival time (``time.time()``). ``capture(not_before=t)`` returns the first
frame that *arrived* at least one frame period (plus ``FRESH_MARGIN_S`` and the rig
file's ``latency_s``) after ``t``, and arrived live: the grabber had waited for it (see
``LIVE_GAP``). A grabber descheduled on a busy host reads a backlog of older frames in a
burst, each stamped late; a loaded run once took a frame of the head mid-roll that way.
a frame arriving that late was exposed after ``t``, even counting the exposure, encode
and transport latency of a USB or network camera. We chose the grabber over flushing
buffered frames because the depth of V4L2 and FFMPEG buffers differs by driver and
cannot be flushed reliably; a reader that always drains them sidesteps the question.

Decoding: from an MJPEG stream the grabber keeps each frame as its JPEG bytes (OpenCV's
raw mode, ``CAP_PROP_FORMAT`` -1) and a frame is decoded, straight to grey, only when a
capture looks at it. Decoding all 15 frames a second to colour cost the process 4.7 ms of
CPU per frame; reading the bytes costs 0.14 ms. The grey levels agree with FFmpeg's colour
decode turned grey within one level (on 1.4 % of pixels). Other streams and V4L2 devices
are decoded by OpenCV as they arrive.

Failures: no new frame within ``timeout_s`` raises ``DeviceError`` (stalled or vanished
stream), never a hang.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import cv2
import numpy as np

from rigctl.drivers.base import Camera, DeviceError, Frame, load_note
from rigctl.drivers.v4l2_controls import V4L2Controls, device_path

log = logging.getLogger(__name__)

FRESH_MARGIN_S = 0.02
# After a motion only a *live* frame counts: one the grabber waited for (at least this
# fraction of a frame period since the previous read), not one drained from a backlog.
LIVE_GAP = 0.3


def _cells(img) -> np.ndarray:
    """The frame in grey, 8x downsampled (area): 8 x 8 pixel cells."""
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    return cv2.resize(grey.astype("float32"), (grey.shape[1] // 8, grey.shape[0] // 8),
                      interpolation=cv2.INTER_AREA)


def mean_change(a, b) -> float:
    """Mean absolute grey-level change between two frames, 8x downsampled (area), so
    that sensor noise averages out (a noise of 2 grey levels leaves ~0.3)."""
    return float(cv2.absdiff(_cells(a), _cells(b)).mean())


def changed_share(a, b, level: float = 8.0) -> float:
    """The share of 8 x 8 pixel cells whose mean grey level changed by more than
    ``level`` between two frames. Sensor noise of 2 grey levels moves a cell by about
    0.25, so a still scene leaves none; a small move of a sparse scene (thin contours on
    a plain background) changes few cells, but by far more than ``level``."""
    return float(np.mean(cv2.absdiff(_cells(a), _cells(b)) > level))
CONTROL_PROPS = {
    "exposure": cv2.CAP_PROP_EXPOSURE, "gain": cv2.CAP_PROP_GAIN,
    "focus": cv2.CAP_PROP_FOCUS, "white_balance": cv2.CAP_PROP_WB_TEMPERATURE,
    "brightness": cv2.CAP_PROP_BRIGHTNESS, "contrast": cv2.CAP_PROP_CONTRAST,
}


class Picture:
    """One frame as the grabber read it: an image, or (``encoded``) the JPEG bytes of one,
    decoded to grey on the first look and kept."""

    __slots__ = ("_data", "_encoded", "_grey", "_source")

    def __init__(self, data: np.ndarray, encoded: bool, source: str = "camera") -> None:
        self._data, self._encoded, self._grey, self._source = data, encoded, None, source

    @property
    def grey(self) -> np.ndarray:
        """The frame in grey (uint8, h x w); ``DeviceError`` if the bytes are no image."""
        if self._grey is None:
            if self._encoded:
                grey = cv2.imdecode(self._data.reshape(-1), cv2.IMREAD_GRAYSCALE)
                if grey is None:
                    raise DeviceError(f"{self._source}: a frame of {self._data.size} bytes "
                                      "from the stream is not a JPEG image")
            else:
                data = self._data
                grey = cv2.cvtColor(data, cv2.COLOR_BGR2GRAY) if data.ndim == 3 else data
            self._grey = grey
        return self._grey


def fourcc_text(value: float) -> str:
    code = int(value)
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))


class OpenCVCamera(Camera):
    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.cap: cv2.VideoCapture | None = None
        self.is_stream = isinstance(cfg.device, str) and "://" in cfg.device
        self.settings: dict[str, Any] = {}
        self._cond = threading.Condition()
        self._latest: tuple[Any, float, int, bool] | None = None
        self._error: str | None = None
        self._running = False
        self._thread: threading.Thread | None = None
        self.fps = cfg.fps or 15.0
        self.encoded = False  # the grabber keeps JPEG bytes (an MJPEG stream in raw mode)

    @property
    def name(self) -> str:
        return f"camera {self.cfg.device}"

    def open(self) -> None:
        """Open the device (``open_retries`` more tries, 0.5 s apart, doubling), apply the
        settings and check that a frame of the configured size arrives."""
        for attempt in range(self.cfg.open_retries + 1):
            if attempt:
                time.sleep(0.5 * 2 ** (attempt - 1))
            cap = self._open_capture()
            if cap.isOpened():
                break
            log.warning("%s: open attempt %d/%d failed", self.name, attempt + 1,
                        self.cfg.open_retries + 1)
        else:
            raise DeviceError(f"{self.name}: cannot open (no such device, or stream not "
                              f"reachable) after {self.cfg.open_retries + 1} tries; "
                              f"{load_note('devices.camera.timeout_s and open_retries')}")
        self.cap = cap
        self._apply_settings()
        self._running = True
        self._thread = threading.Thread(target=self._grab, daemon=True, name="camera-grab")
        self._thread.start()
        frame = self.capture()  # also checks the actual frame shape
        self.settings["actual_shape"] = list(frame.image.shape)

    def _open_capture(self) -> cv2.VideoCapture:
        timeout_ms = int(self.cfg.timeout_s * 1000)
        if self.is_stream:
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms,
                      cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms]
            cap = cv2.VideoCapture(self.cfg.device, cv2.CAP_FFMPEG, params)
        else:
            device = self.cfg.device
            if isinstance(device, str) and device.isdigit():
                device = int(device)
            cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        return cap

    def _apply_settings(self) -> None:
        cap, cfg = self.cap, self.cfg
        failed = []
        if self.is_stream:
            self._stream_settings()
            return
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*cfg.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, cfg.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height)
        if cfg.fps:
            cap.set(cv2.CAP_PROP_FPS, cfg.fps)
        v4l2 = self._v4l2_controls()
        if cfg.auto_off and v4l2 is None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual exposure
            cap.set(cv2.CAP_PROP_AUTOFOCUS, 0)
            cap.set(cv2.CAP_PROP_AUTO_WB, 0)
        for name, value in cfg.controls.items():
            cap.set(CONTROL_PROPS[name], value)
        got = {"fourcc": fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
               "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
               "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))}
        if got["fourcc"] != cfg.fourcc:
            failed.append(f"fourcc {cfg.fourcc} (got {got['fourcc']})")
        if (got["width"], got["height"]) != (cfg.width, cfg.height):
            failed.append(f"size {cfg.width}x{cfg.height} (got {got['width']}x{got['height']})")
        for name, value in cfg.controls.items():
            read = cap.get(CONTROL_PROPS[name])
            got[name] = read
            if abs(read - value) > 1e-6 * max(1.0, abs(value)):
                failed.append(f"{name} {value} (got {read})")
        if failed:
            raise DeviceError(f"{self.name}: settings did not take: " + "; ".join(failed))
        self.settings = {"backend": cap.getBackendName(), "device": str(cfg.device), **got}
        if v4l2 is not None:
            self.settings["v4l2"] = v4l2

    def _stream_settings(self) -> None:
        """A stream URL: nothing to set; record what it delivers."""
        cap, cfg = self.cap, self.cfg
        if cfg.controls or cfg.v4l2_controls:
            names = sorted(cfg.controls) + sorted(cfg.v4l2_controls)
            raise DeviceError(f"{self.name}: controls {names} cannot be set on a stream URL; "
                              "remove them from the rig file")
        self.settings = {"backend": cap.getBackendName(), "device": cfg.device,
                         "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                         "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                         "fourcc": "MJPG (stream)"}
        fps = cap.get(cv2.CAP_PROP_FPS)
        if fps and 0 < fps < 240:
            self.fps = cfg.fps or fps
        if fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)) == "MJPG":
            self.encoded = bool(cap.set(cv2.CAP_PROP_FORMAT, -1))
        self.settings["decoded_on_capture"] = self.encoded

    def _v4l2_controls(self) -> dict[str, int] | None:
        """Automatics off and ``v4l2_controls`` set by name through the kernel, every value
        read back (``rigctl.drivers.v4l2_controls``); None where the device is no V4L2 node."""
        path = device_path(self.cfg.device)
        if path is None:
            if self.cfg.v4l2_controls:
                raise DeviceError(f"{self.name}: v4l2_controls need a /dev/video device")
            return None
        controls = V4L2Controls.open(path)
        try:
            return controls.apply(self.cfg.v4l2_controls, self.cfg.auto_off)
        finally:
            controls.close()

    def _grab(self) -> None:
        seq = 0
        previous = time.time()
        while self._running:
            ok, image = self.cap.read()
            arrived = time.time()
            # A read that returned at once came from the backlog of the decoder or the
            # socket (the grabber was descheduled): exposed earlier than it arrived.
            live = arrived - previous >= LIVE_GAP * (1.0 / self.fps)
            previous = arrived
            if not ok:
                with self._cond:
                    self._error = "read failed (stream stalled or device gone)"
                    self._cond.notify_all()
                time.sleep(0.05)
                continue
            seq += 1
            with self._cond:
                self._latest = (Picture(image, self.encoded, self.name), arrived, seq, live)
                self._error = None
                self._cond.notify_all()

    def capture(self, not_before: float | None = None) -> Frame:
        """The newest frame that arrived one frame period after ``not_before`` (or any
        frame newer than the call when ``not_before`` is None)."""
        if self.cap is None:
            raise DeviceError(f"{self.name}: not open")
        threshold = (not_before if not_before is not None else time.time())
        if not_before is not None:
            threshold += 1.0 / self.fps + FRESH_MARGIN_S + self.cfg.latency_s
        deadline = time.monotonic() + self.cfg.timeout_s
        latest = self._wait_frame(lambda f: f[1] >= threshold and (f[3] or not_before is None),
                                  deadline)
        if not_before is not None and self.cfg.still_threshold > 0:
            latest = self._still(latest, deadline)
        picture, arrived, seq, _live = latest
        image = picture.grey
        h, w = image.shape[:2]
        if (w, h) != (self.cfg.width, self.cfg.height):
            raise DeviceError(f"{self.name}: frames are {w}x{h}, the rig file says "
                              f"{self.cfg.width}x{self.cfg.height}")
        return Frame(image, arrived, seq, dict(self.settings))

    def _wait_frame(self, accept, deadline: float):
        """The newest frame once ``accept(frame)`` holds; ``DeviceError`` at the deadline."""
        with self._cond:
            while True:
                latest = self._latest
                if latest is not None and accept(latest):
                    return latest
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    why = self._error or "no new frame"
                    raise DeviceError(f"{self.name}: {why} within {self.cfg.timeout_s:.1f} s; "
                                      f"{load_note('devices.camera.timeout_s')}")
                self._cond.wait(remaining)

    def _still(self, frame, deadline: float):
        """The first frame that the next live frame barely differs from (mean absolute
        change below ``still_threshold`` grey levels on 8x downsampled images): a frame
        exposed while the arm or head was still moving, or delayed in the decoder's
        pipeline past the arrival rule, is passed over."""
        change = float("nan")
        while True:
            try:
                newer = self._wait_frame(lambda f, seq=frame[2]: f[2] > seq and f[3], deadline)
            except DeviceError:
                raise DeviceError(
                    f"{self.name}: the image did not keep still within "
                    f"{self.cfg.timeout_s:.1f} s (mean change {change:.2f} grey levels between "
                    f"frames, devices.camera.still_threshold {self.cfg.still_threshold}): is "
                    f"something moving in view? {load_note('devices.camera.timeout_s')}"
                ) from None
            change = mean_change(frame[0].grey, newer[0].grey)
            if change < self.cfg.still_threshold:
                return newer
            frame = newer

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=self.cfg.timeout_s + 1)
        if self.cap is not None:
            self.cap.release()
            self.cap = None

    def describe(self) -> dict[str, Any]:
        return {"model": "OpenCV " + cv2.__version__, "firmware": None,
                "serial": str(self.cfg.device), "settings": self.settings, "fps": self.fps}
