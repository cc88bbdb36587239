"""Contact sheet of the shipped virtual sensors: the same contacts on every sensor.

``python -m tactile_deploy.sensors.contact_sheet [--out docs/img/optics_virtual_sensors.png]``
renders, for each shipped sensor, its reference frame and three contacts (a 4 mm sphere, the
cross and the 9 x 7 pin grid), each with noise, and writes them as one figure (matplotlib).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tactile_deploy.atomic import atomic_path
from tactile_deploy.indenters import ContactPose
from tactile_deploy.indenters.pin_grid import PinGrid
from tactile_deploy.sensors.catalog import list_sensors, load_sensor

ROOT = Path(__file__).resolve().parents[2]


def contact_sheet(path: Path, sensors=None, seed: int = 0) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(sensors or list_sensors())
    contacts = [("sphere_r4", ContactPose(x_mm=1.0, y_mm=0.5, depth_mm=0.6), "sphere r 4 mm"),
                ("cross", ContactPose(x_mm=-0.5, y_mm=0.0, theta_deg=20.0, depth_mm=0.5),
                 "cross"),
                (PinGrid(), ContactPose(depth_mm=0.35), "pin grid")]
    fig, axes = plt.subplots(len(names), 1 + len(contacts),
                             figsize=(3.0 * (1 + len(contacts)), 2.6 * len(names)))
    axes = np.atleast_2d(axes)
    for i, name in enumerate(names):
        sensor = load_sensor(name)
        rng = np.random.default_rng([seed, i])
        frames = [("reference", sensor.reference_frame(rng))]
        for ind, pose, label in contacts:
            frames.append((label, sensor.press(ind, pose, rng, truth=False).frame))
        for k, (label, frame) in enumerate(frames):
            ax = axes[i, k]
            ax.imshow(frame)
            ax.set_title(f"{name}: {label}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" /
                    "optics_virtual_sensors.png")
    args = ap.parse_args(argv)
    contact_sheet(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
