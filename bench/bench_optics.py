"""RGB frames/s of the optics renderer on one CPU core, against a direct per-light baseline.

    python bench/bench_optics.py [--sensor gelslim1] [--repeats 20] [--small]
    (or: tactile-deploy bench optics)

Measures, in one run on this machine, one thread (OpenCV and BLAS limited to 1):

* the renderer (:class:`tactile_deploy.optics.OpticsRenderer`) shading a whole 640 x 480 frame
  (height map -> slopes -> remap -> LEDs -> noise -> 8-bit), the worst case;
* the same for a typical contact (a 4 mm sphere 0.6 mm deep), where only the changed region is
  shaded;
* the baseline: the same equations written directly (``radiance_reference``: float64, one light
  at a time, camera mapping and per-pixel terms recomputed, scipy sampling) plus the same noise
  and quantisation;
* the whole virtual sensor (FEM contact + fine surface + frame) in frames/s.

The renderer and the baseline agree to the reported difference (grey levels, noise-free).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _best(fn, repeats: int) -> float:
    """Median wall time of ``fn()`` over ``repeats`` calls (after one warm-up), s."""
    import numpy as np

    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def run(sensor_name: str = "gelslim1", repeats: int = 20, small: bool = False) -> dict:
    import cv2
    import numpy as np
    from threadpoolctl import threadpool_limits

    from tactile_deploy.indenters import AnalyticSphere, ContactPose
    from tactile_deploy.optics import simple_camera
    from tactile_deploy.optics.render import OpticsRenderer, radiance_reference
    from tactile_deploy.sensors import sensor_config

    cfg = sensor_config(sensor_name)
    if small:  # test settings: a 160 x 120 camera
        cam = simple_camera(160, 120, 0.15, k1=-0.1)
        cfg = cfg.model_copy(update={"optics": cfg.optics.model_copy(update={"camera": cam})})
    from tactile_deploy.sensors.virtual import VirtualSensor

    sensor = VirtualSensor(cfg)
    sensor.prepare()
    renderer: OpticsRenderer = sensor.renderer
    pose = ContactPose(x_mm=1.0, y_mm=-0.5, depth_mm=0.6)
    ball = AnalyticSphere(4.0)
    out = sensor.press(ball, pose)
    contact_height = (renderer.rest_height_mm - out.surface_depth_mm).astype(np.float32)
    # A whole-frame change: a long shallow wave over the view (every pixel differs from rest).
    from tactile_deploy.optics.render import grid_centres

    x, y = grid_centres(renderer.grid)
    wave = (renderer.rest_height_mm - 0.05 * (1 + np.sin(x / 1.5) * np.cos(y / 2.0))).astype(
        np.float32)
    rng = np.random.default_rng(0)
    roi = renderer.changed_roi(contact_height)
    h, w = renderer.shape
    roi_fraction = 0.0 if roi is None else (roi[1] - roi[0]) * (roi[3] - roi[2]) / (h * w)

    def baseline():
        rad = radiance_reference(renderer.model, renderer.grid, wave).astype(np.float32)
        rad = cv2.GaussianBlur(rad, (0, 0), renderer.model.blur_sigma_px) if \
            renderer.model.blur_sigma_px > 0 else rad
        return renderer.finish(rad, rng)

    old_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1):
            t_full = _best(lambda: renderer.render(wave, rng), repeats)
            t_contact = _best(lambda: renderer.render(contact_height, rng), repeats)
            t_base = _best(baseline, max(2, repeats // 10))
            t_sensor = _best(lambda: sensor.press(ball, pose, rng, truth=False), max(3, repeats // 4))
    finally:
        cv2.setNumThreads(old_threads)
    diff = float(np.abs(renderer.radiance(wave)
                        - radiance_reference(renderer.model, renderer.grid, wave)).max())
    import os

    return {
        "load_average": os.getloadavg()[0],
        "sensor": cfg.name, "width_px": w, "height_px": h,
        "lights": len(cfg.optics.lights),
        "full_frame_fps": 1.0 / t_full, "full_frame_ms": 1e3 * t_full,
        "contact_frame_fps": 1.0 / t_contact, "contact_frame_ms": 1e3 * t_contact,
        "contact_region_fraction": roi_fraction,
        "baseline_fps": 1.0 / t_base, "baseline_ms": 1e3 * t_base,
        "speedup_full": t_base / t_full,
        "sensor_fps": 1.0 / t_sensor, "sensor_ms": 1e3 * t_sensor,
        "max_difference_grey": diff,
    }


def markdown(r: dict) -> str:
    from bench.report import machine_line

    return "\n".join([
        "## RGB frames of a virtual sensor (`tactile-deploy bench optics`)",
        "",
        (f"CPU: {machine_line()}; one thread (OpenCV and BLAS); load average "
        f"{r['load_average']:.1f} on the machine's 2 cores while measuring. Sensor `{r['sensor']}`: "
        f"{r['width_px']} x {r['height_px']} px, {r['lights']} LEDs, blur, shot and read noise, "
        "8-bit."),
        "",
        "| path | ms per frame | frames/s | vs baseline |",
        "|---|---|---|---|",
        (f"| direct per-light equations, float64 (baseline) | {r['baseline_ms']:.0f} | "
        f"{r['baseline_fps']:.1f} | 1x |"),
        (f"| renderer, whole frame changed | {r['full_frame_ms']:.1f} | {r['full_frame_fps']:.0f} | "
        f"{r['speedup_full']:.0f}x |"),
        (f"| renderer, one contact (4 mm sphere, {100 * r['contact_region_fraction']:.0f} % of the "
        f"frame shaded) | {r['contact_frame_ms']:.1f} | {r['contact_frame_fps']:.0f} | "
        f"{r['baseline_ms'] / r['contact_frame_ms']:.0f}x |"),
        (f"| whole virtual sensor: FEM contact + fine surface + frame | {r['sensor_ms']:.0f} | "
        f"{r['sensor_fps']:.1f} | |"),
        "",
        (f"Renderer and baseline agree to {r['max_difference_grey']:.3f} grey levels (noise-free "
        "radiance). Timings are medians over repeated frames; the machine's other load adds "
        "noise (+-20 %)."),
    ])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sensor", default="gelslim1")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--small", action="store_true", help="quick run: 160 x 120 camera")
    parser.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = parser.parse_args(argv)
    if args.small:
        args.repeats = 3
    result = run(args.sensor, args.repeats, args.small)
    text = markdown(result)
    print(text)
    if not args.no_write and not args.small:
        from bench.report import write_section

        write_section("optics", text)
    return result


if __name__ == "__main__":
    main()
