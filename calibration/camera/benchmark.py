"""Benchmark: ``rectify`` of a raw camera frame onto the 128 x 128 sensor grid, one CPU thread.

``python -m tactile_deploy.calibration.camera.benchmark`` prints the median time per call over many calls for
grey and colour uint8 frames at 640 x 480, with float and fixed-point (:func:`compact_remap`)
tables, and the one-off cost of :func:`build_remap`.
``--small`` runs a few calls only (a smoke test of the benchmark itself).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from tactile_deploy.imaging.camera_mapping import (
    build_remap,
    camera_mapping_from_parameters,
    compact_remap,
    rectify,
)


def _median_us(fn, n_calls: int) -> float:
    for _ in range(min(20, n_calls)):
        fn()
    times = np.empty(n_calls)
    for i in range(n_calls):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1e6)


def run(n_calls: int = 2000, threads: int = 1) -> dict[str, float]:
    """Median microseconds per call: ``rectify_{gray,bgr}_us`` (float tables),
    ``rectify_{gray,bgr}_compact_us`` (fixed-point tables), ``build_remap_us``.
    ``threads`` sets OpenCV's thread count for the measurement."""
    k = np.array([[520.0, 0.0, 322.0], [0.0, 520.0, 241.0], [0.0, 0.0, 1.0]])
    s2u = np.array([[1 / 0.07, 0.0, 319.5], [0.0, 1 / 0.075, 239.5], [0.0, 0.0, 1.0]])
    mapping = camera_mapping_from_parameters((640, 480), k, [-0.3, 0.1, 0.001, -0.0005, 0.0],
                                             np.linalg.inv(s2u))
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (480, 640), dtype=np.uint8)
    bgr = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    previous = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        remap = build_remap(mapping)
        compact = compact_remap(remap)
        return {
            "rectify_gray_us": _median_us(lambda: rectify(gray, mapping, remap), n_calls),
            "rectify_bgr_us": _median_us(lambda: rectify(bgr, mapping, remap), n_calls),
            "rectify_gray_compact_us": _median_us(lambda: rectify(gray, mapping, compact), n_calls),
            "rectify_bgr_compact_us": _median_us(lambda: rectify(bgr, mapping, compact), n_calls),
            "build_remap_us": _median_us(lambda: build_remap(mapping), max(3, n_calls // 100)),
        }
    finally:
        cv2.setNumThreads(previous)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", help="a few calls only")
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    args = parser.parse_args()
    result = run(n_calls=20 if args.small else 2000, threads=args.threads)
    for key, value in result.items():
        print(f"{key:>24}: {value:9.1f} us")
