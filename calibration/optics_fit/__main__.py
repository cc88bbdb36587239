"""``python -m tactile_deploy.calibration.optics_fit``: fit the optics model to the real FOTS presses and write
the fitted virtual sensor, the comparison table and ``docs/img/optics_real_vs_sim.png``."""

from __future__ import annotations

import json
from pathlib import Path

from tactile_deploy.calibration.optics_fit.fots import (
    ROOT,
    fit_fots,
    fots_figure,
    fots_sensor_config,
    load_fots,
    markdown_table,
)


def main(argv=None) -> int:
    import argparse

    from tactile_deploy.sensors.config import SENSOR_DIR, save_sensor_config

    ap = argparse.ArgumentParser(description="Fit the optics model to the real FOTS presses.")
    ap.add_argument("--figure", type=Path, default=ROOT / "docs" / "img" /
                    "optics_real_vs_sim.png")
    ap.add_argument("--sensor", type=Path, default=SENSOR_DIR / "gelsight_fots.json",
                    help="where to write the gelsight_fots virtual sensor")
    ap.add_argument("--no-write", action="store_true", help="print the figures only")
    args = ap.parse_args(argv)
    press = load_fots()
    report = fit_fots(press)
    print(markdown_table(report))
    print(json.dumps({"sinking_scale": report.sinking_scale, "fem": report.fem,
                      "train": report.train, "n_samples": report.fit.n_samples,
                      "evaluations": report.fit.n_evaluations,
                      "train_rmse_grey": report.fit.rmse_grey,
                      "lights": [lt.model_dump() for lt in report.model.lights],
                      "ambient_grey": report.model.ambient_grey,
                      "vignetting": report.model.vignetting.model_dump()}, indent=1))
    if not args.no_write:
        fots_figure(report, press, args.figure)
        save_sensor_config(fots_sensor_config(report), args.sensor)
        print(f"wrote {args.figure} and {args.sensor}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
