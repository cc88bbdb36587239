"""A live camera through OpenCV, by index or device path, with reconnection and drop counting.

A background thread reads the camera as fast as it delivers and keeps only the newest frame, so
``read()`` always returns the freshest image (lowest latency) and frames that were captured but
replaced before anyone read them are counted in ``stats.dropped``.

On opening, the camera is asked for the configured frame size, rate and pixel format; exposure
and white balance are set as configured (automatic, locked after ``settle_s`` of automatic, or
manual values); then what the camera reports it delivers is read back into :attr:`settings`
(logged; a size or rate other than asked is a warning, since the plugin's camera mapping expects
its size). The device may be an index, a path (``/dev/v4l/by-id/...`` links are resolved) or
``serial:SERIAL`` (:func:`~tactile_deploy.runtime.sources.devices.resolve_camera`).

When the camera stops delivering (unplugged, driver reset) the thread releases it and tries to
reopen it, waiting 0.1 s, 0.2 s, 0.4 s, ... (at most ``max_backoff_s``) between attempts, for up
to ``reconnect_timeout_s``; each outage and each recovery is logged. If the camera does not come
back in time, the next ``read()`` raises :class:`SourceDisconnectedError`.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from tactile_deploy.runtime.sources.base import (
    Frame,
    FrameSource,
    SourceDisconnectedError,
    SourceError,
    now_ns,
)
from tactile_deploy.runtime.sources.config import CameraSourceConfig

log = logging.getLogger(__name__)

#: First wait between reopening attempts, s (doubles up to ``max_backoff_s``).
FIRST_BACKOFF_S = 0.1


def _default_capture(device):
    import cv2

    if isinstance(device, str) and device.startswith("/dev/"):
        return cv2.VideoCapture(device, cv2.CAP_V4L2)       # a path: V4L2, not a file reader
    return cv2.VideoCapture(device)


#: V4L2 values of OpenCV's CAP_PROP_AUTO_EXPOSURE (the V4L2 backend passes them through).
V4L2_EXPOSURE_MANUAL = 1
V4L2_EXPOSURE_AUTO = 3


def fourcc_text(code: float) -> str:
    """OpenCV's CAP_PROP_FOURCC number as its four characters ('' when unknown)."""
    c = int(code)
    text = "".join(chr((c >> 8 * i) & 0xFF) for i in range(4))
    return text if c and text.isprintable() else ""


class OpenCVCamera(FrameSource):
    """Camera source (see the module docstring).

    config : :class:`CameraSourceConfig`.
    capture_factory : ``device -> capture`` with OpenCV's ``VideoCapture`` interface
        (``isOpened``, ``read``, ``set``, ``get``, ``release``); tests pass fakes.
    sleep : the wait function used between reopening attempts (tests pass a fast one).
    """

    finite = False
    live = True

    def __init__(self, config: CameraSourceConfig, capture_factory=None, sleep=time.sleep):
        super().__init__()
        self.config = config
        self.name = f"camera {config.device}"
        self._factory = capture_factory or _default_capture
        self._sleep = sleep
        self._cap = None
        self._cond = threading.Condition()
        self._latest: tuple[np.ndarray, tuple[int, int]] | None = None
        self._error: BaseException | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reconnecting = False
        #: what the camera was asked and what it reports delivering (:meth:`_configure`).
        self.settings: dict = {}

    # ------------------------------------------------------------------ opening
    def _try_open(self):
        from tactile_deploy.runtime.sources.devices import CameraNotFoundError, resolve_camera

        try:
            device = resolve_camera(self.config.device)
        except CameraNotFoundError as e:
            raise SourceError(str(e)) from None
        cap = self._factory(device)
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            return None
        self._configure(cap)
        return cap

    def _configure(self, cap) -> None:
        """Ask for size, rate, format, exposure and white balance; read back what was given."""
        import cv2

        c = self.config
        refused = []

        def ask(prop, value, what):
            if not cap.set(prop, value):
                refused.append(what)

        if c.fourcc:
            ask(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*c.fourcc), "pixel format")
        if c.width_px:
            ask(cv2.CAP_PROP_FRAME_WIDTH, c.width_px, "width")
        if c.height_px:
            ask(cv2.CAP_PROP_FRAME_HEIGHT, c.height_px, "height")
        if c.fps:
            ask(cv2.CAP_PROP_FPS, c.fps, "frame rate")
        locks = []
        if c.exposure is not None:
            auto = c.exposure in ("auto", "lock")
            ask(cv2.CAP_PROP_AUTO_EXPOSURE,
                V4L2_EXPOSURE_AUTO if auto else V4L2_EXPOSURE_MANUAL, "exposure mode")
            if not auto:
                ask(cv2.CAP_PROP_EXPOSURE, float(c.exposure), "exposure")
            elif c.exposure == "lock":
                locks.append((cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL,
                              cv2.CAP_PROP_EXPOSURE, "exposure"))
        if c.white_balance is not None:
            auto = c.white_balance in ("auto", "lock")
            ask(cv2.CAP_PROP_AUTO_WB, 1 if auto else 0, "white balance mode")
            if not auto:
                ask(cv2.CAP_PROP_WB_TEMPERATURE, float(c.white_balance), "white balance")
            elif c.white_balance == "lock":
                locks.append((cv2.CAP_PROP_AUTO_WB, 0, cv2.CAP_PROP_WB_TEMPERATURE,
                              "white balance"))
        if locks:
            # let the automatic controls settle on real frames, then fix what they chose
            t_end = time.monotonic() + c.settle_s
            while time.monotonic() < t_end:
                cap.read()
            for mode_prop, manual, value_prop, what in locks:
                chosen = cap.get(value_prop)
                ask(mode_prop, manual, f"{what} mode")
                ask(value_prop, chosen, what)
        self.settings = self._delivered(cap, refused)
        self._report()

    def _delivered(self, cap, refused: list[str]) -> dict:
        import cv2

        c = self.config
        got = {"width_px": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
               "height_px": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
               "fps": round(float(cap.get(cv2.CAP_PROP_FPS)), 3),
               "fourcc": fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
               "auto_exposure": float(cap.get(cv2.CAP_PROP_AUTO_EXPOSURE)),
               "exposure": float(cap.get(cv2.CAP_PROP_EXPOSURE)),
               "auto_white_balance": float(cap.get(cv2.CAP_PROP_AUTO_WB)),
               "white_balance_k": float(cap.get(cv2.CAP_PROP_WB_TEMPERATURE))}
        asked = {"width_px": c.width_px, "height_px": c.height_px, "fps": c.fps,
                 "fourcc": c.fourcc, "exposure": c.exposure, "white_balance": c.white_balance}
        return {"device": str(self.config.device), "asked": asked, "delivered": got,
                "refused": refused}

    def _report(self) -> None:
        s, c = self.settings, self.config
        got = s["delivered"]
        log.info("%s delivers %dx%d px %s at %g fps (exposure %g, auto %g; white balance %g K, "
                 "auto %g)", self.name, got["width_px"], got["height_px"], got["fourcc"] or "?",
                 got["fps"], got["exposure"], got["auto_exposure"], got["white_balance_k"],
                 got["auto_white_balance"])
        off = [f"{k} {got[k]:g} (asked {v:g})" for k, v in
               (("width_px", c.width_px), ("height_px", c.height_px), ("fps", c.fps))
               if v and abs(got[k] - v) > 1e-3 * v]
        if c.fourcc and got["fourcc"] and got["fourcc"] != c.fourcc:
            off.append(f"pixel format {got['fourcc']} (asked {c.fourcc})")
        if off or s["refused"]:
            refused = f"; refused: {', '.join(s['refused'])}" if s["refused"] else ""
            log.warning("%s does not deliver what was asked: %s%s", self.name,
                        ", ".join(off) or "-", refused)

    def _open(self) -> None:
        self._cap = self._try_open()
        if self._cap is None:
            raise SourceError(
                f"{self.name} could not be opened: check that it is plugged in and not used by "
                "another program (`tactile-deploy cameras` lists the cameras here), or "
                "pass another --source"
            )
        self._stop.clear()
        self._error = None
        self._latest = None
        self._thread = threading.Thread(target=self._grab_loop, name=f"grab {self.name}",
                                        daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ grabbing
    def _grab_loop(self) -> None:
        try:
            while not self._stop.is_set():
                ok, img = self._cap.read()
                if not ok or img is None:
                    self._reconnect()
                    continue
                stamp = now_ns()
                with self._cond:
                    if self._latest is not None:
                        self.stats.dropped += 1
                    self._latest = (img, stamp)
                    self._cond.notify_all()
        except BaseException as exc:  # handed to the reader
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    def _reconnect(self) -> None:
        c = self.config
        t0 = time.monotonic()
        log.warning("%s stopped delivering frames; trying to reopen it for up to %.1f s",
                    self.name, c.reconnect_timeout_s)
        with self._cond:
            self._reconnecting = True
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        wait = FIRST_BACKOFF_S
        attempts = 0
        waited = 0.0
        while not self._stop.is_set():
            if waited >= c.reconnect_timeout_s:
                raise SourceDisconnectedError(
                    f"{self.name} disappeared and did not come back within "
                    f"{c.reconnect_timeout_s:g} s ({attempts} attempts to reopen it); check the "
                    "cable and the USB hub, then run again (a longer wait: reconnect_timeout_s "
                    "in the plugin's default_source)"
                )
            step = min(wait, c.max_backoff_s, max(c.reconnect_timeout_s - waited, 0.0))
            self._sleep(step)
            waited += step
            wait *= 2.0
            attempts += 1
            cap = self._try_open()
            if cap is not None:
                self._cap = cap
                self.stats.reconnects += 1
                outage = time.monotonic() - t0
                self.stats.extra["outage_s"] = self.stats.extra.get("outage_s", 0.0) + outage
                log.warning("%s is back after %d attempt(s) (%.2f s)", self.name, attempts,
                            outage)
                with self._cond:
                    self._reconnecting = False
                return

    # ------------------------------------------------------------------ reading
    def _read(self) -> Frame | None:
        import cv2

        c = self.config
        limit = max(c.reconnect_timeout_s, 0.0) + 5.0
        deadline = time.monotonic() + limit
        with self._cond:
            while self._latest is None and self._error is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    if self._reconnecting:
                        deadline = time.monotonic() + limit
                        continue
                    raise SourceError(f"{self.name} delivered no frame for {limit:.0f} s; check "
                                      "its exposure and frame-rate settings")
                self._cond.wait(min(remaining, 0.5))
            if self._latest is None:
                err = self._error
                raise err if isinstance(err, SourceError) else SourceError(
                    f"{self.name} failed: {err!r}")
            img, stamp = self._latest
            self._latest = None
        if img.ndim == 2:
            rgb = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        else:
            rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        return self._frame(rgb, None, stamp)

    def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._cap is not None:
            self._cap.release()
            self._cap = None
