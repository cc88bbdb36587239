"""Video devices of this computer, as Linux describes them (V4L2 through sysfs and udev links).

:func:`list_cameras` reads ``/sys/class/video4linux/videoN`` (``name``, ``index``: the node's
number within its device, 0 for the image stream, higher ones often metadata) and the USB device
above it (``serial``, ``idVendor``, ``idProduct``, ``manufacturer``, ``product``), and matches
the stable links udev makes in ``/dev/v4l/by-id`` and ``/dev/v4l/by-path``. Nothing is opened.
:func:`resolve_camera` turns ``serial:ABC123`` or a by-id path into the device path, so a sensor
is found whatever order the cameras were plugged in.

Other systems (macOS, Windows) have no such tree: there ``cameras`` lists nothing and cameras
are chosen by index.
"""

from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path

SYSFS = Path("/sys/class/video4linux")
DEV = Path("/dev")


@dataclass(frozen=True)
class CameraDevice:
    """One V4L2 device node.

    index : N of /dev/videoN (what ``--source N`` opens). path : /dev/videoN.
    name : the driver's name of the device. node_index : the node's number within its physical
        device (0: the image stream; >0: usually metadata, not a camera image).
    serial, vendor_id, product_id, manufacturer, product : of the USB device, when it says.
    by_id, by_path : the udev links to this node, when they exist.
    """

    index: int
    path: str
    name: str
    node_index: int | None = None
    serial: str | None = None
    vendor_id: str | None = None
    product_id: str | None = None
    manufacturer: str | None = None
    product: str | None = None
    by_id: str | None = None
    by_path: str | None = None

    @property
    def is_image_node(self) -> bool:
        return self.node_index in (None, 0)

    def as_dict(self) -> dict:
        return asdict(self)


def _read(path: Path) -> str | None:
    try:
        text = path.read_text(errors="replace").strip()
    except OSError:
        return None
    return text or None


def _usb_attributes(device_dir: Path) -> dict:
    """serial, ids and names of the USB device above a V4L2 node's ``device`` link."""
    try:
        d = device_dir.resolve()
    except OSError:
        return {}
    for _ in range(4):                      # interface dir -> device dir (holds idVendor)
        if (d / "idVendor").exists():
            return {"serial": _read(d / "serial"), "vendor_id": _read(d / "idVendor"),
                    "product_id": _read(d / "idProduct"),
                    "manufacturer": _read(d / "manufacturer"), "product": _read(d / "product")}
        d = d.parent
    return {}


def _links(folder: Path) -> dict[str, str]:
    """{resolved target: link path} of the symlinks in a /dev/v4l/by-* folder."""
    out: dict[str, str] = {}
    if not folder.is_dir():
        return out
    for link in sorted(folder.iterdir()):
        try:
            target = os.path.realpath(link)
        except OSError:
            continue
        out.setdefault(target, str(link))
    return out


def list_cameras(sysfs: Path = SYSFS, dev: Path = DEV) -> list[CameraDevice]:
    """The V4L2 device nodes, by index (module docstring). ``sysfs`` and ``dev`` are the roots
    to read (tests pass a fake tree)."""
    sysfs, dev = Path(sysfs), Path(dev)
    if not sysfs.is_dir():
        return []
    by_id = _links(dev / "v4l" / "by-id")
    by_path = _links(dev / "v4l" / "by-path")
    found = []
    for entry in sysfs.iterdir():
        m = re.fullmatch(r"video(\d+)", entry.name)
        if not m:
            continue
        node = dev / entry.name
        real = os.path.realpath(node)
        node_index = _read(entry / "index")
        found.append(CameraDevice(
            index=int(m.group(1)), path=str(node), name=_read(entry / "name") or "?",
            node_index=int(node_index) if node_index and node_index.isdigit() else None,
            **_usb_attributes(entry / "device"), by_id=by_id.get(real), by_path=by_path.get(real)))
    return sorted(found, key=lambda c: c.index)


class CameraNotFoundError(LookupError):
    """No camera matches a serial number (the message lists the cameras there are)."""


def resolve_camera(device: int | str, sysfs: Path = SYSFS, dev: Path = DEV) -> int | str:
    """The device to open for ``device``: an index stays an index; ``serial:XYZ`` becomes the
    image node (node index 0) of the USB camera with that serial; a path (``/dev/v4l/by-id/...``,
    ``/dev/video2``) is resolved through its links to ``/dev/videoN``."""
    if isinstance(device, int):
        return device
    if device.startswith("serial:"):
        serial = device.split(":", 1)[1]
        cams = list_cameras(sysfs, dev)
        match = [c for c in cams if c.serial == serial and c.is_image_node]
        if not match:
            have = ", ".join(f"{c.path} ({c.name}, serial {c.serial})" for c in cams
                             if c.is_image_node) or "none"
            raise CameraNotFoundError(f"no camera with serial {serial!r}; cameras here: {have} "
                                      "(`tactile-deploy cameras` lists them)")
        return match[0].path
    path = Path(device)
    if str(path).startswith(str(dev)) and path.is_symlink():
        return os.path.realpath(path)
    return device


def describe(cams: list[CameraDevice]) -> list[list[str]]:
    """Rows of the ``tactile-deploy cameras`` table."""
    rows = []
    for c in cams:
        usb = f"{c.vendor_id}:{c.product_id}" if c.vendor_id else ""
        kind = "image" if c.is_image_node else "metadata?"
        rows.append([str(c.index), c.path, c.name, kind, c.serial or "", usb, c.by_id or ""])
    return rows
