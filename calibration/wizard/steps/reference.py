"""Step 1, reference: frames with nothing touching the sensor, averaged."""

from __future__ import annotations

import numpy as np

from tactile_deploy.calibration.wizard.context import Context, Outcome
from tactile_deploy.calibration.wizard.figures import reference_figure
from tactile_deploy.calibration.wizard.work_data import mean_frame, write_png
from tactile_deploy.atomic import write_npz


def step_reference(ctx: Context) -> Outcome:
    """Average frames with nothing touching the sensor."""
    n = ctx.config.reference.n_frames
    st = ctx.station
    if st.rig is not None:
        st.rig.retract()
    else:
        st.release(ctx.ui)
    frames = st.grab(n)
    ref = mean_frame(frames)
    write_npz(ctx.work.path("reference.npz"), reference=ref, frames=frames)
    write_png(ctx.work.path("reference.png"), ref)
    noise = float(np.median(frames.astype(np.float32).std(axis=0))) if n > 1 else float("nan")
    sat = float(np.mean(np.any(ref >= 254, axis=-1)))
    notes = []
    if n > 1 and noise == 0:
        notes.append("the frames are identical: is the source a still image? The noise "
                     "reference will be zero")
    if sat > 0.05:
        notes.append(f"{100 * sat:.1f} % of the reference pixels are saturated: lower the LED "
                     "brightness or the exposure")
    fig = reference_figure(ctx.work.figures / "reference.png", ref, frames)
    h, w = ref.shape[:2]
    metrics = {"frames averaged": n, "image size (px)": f"{w} x {h}",
               "camera noise, median per-pixel std (grey)": noise,
               "saturated pixels (%)": 100 * sat,
               "mean colour (R, G, B grey)": ", ".join(f"{v:.0f}" for v in
                                                       ref.reshape(-1, 3).mean(0))}
    return Outcome(metrics, [fig], notes)
